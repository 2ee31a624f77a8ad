pub mod dpcm;
pub mod render;
