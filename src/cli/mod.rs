pub mod dpcm;
