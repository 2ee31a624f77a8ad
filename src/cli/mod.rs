pub mod dpcm;
pub mod render;
#[cfg(feature = "mcap")]
pub mod replay;
pub mod session;
