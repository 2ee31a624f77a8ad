pub mod dpcm;
pub mod render;
pub mod session;
