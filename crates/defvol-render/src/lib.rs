//! Raycast images: cameras, transfer functions (with pre-integration), and two raycasters,
//! each a part with its CPU path, GPU twin, shader and agreement tests: [`volume`], a
//! regular grid, and [`mesh`], a tetrahedral mesh, which also shows the source volume
//! through the deformed mesh ([`mesh::source`]); both shaders share `camera_tools.wgsl`
//! and `grid_gradient.wgsl`. [`engine`] runs either on the run's backend.

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub mod camera;
pub mod engine;
pub mod mesh;
pub mod transfer;
pub mod volume;

use std::io::BufWriter;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderError {
    #[error("camera: {0}")]
    Camera(String),
    #[error("transfer function: {0}")]
    TransferFunction(String),
    #[error("unknown transfer-function preset `{0}` (ct_soft_tissue, ct_bone, mri)")]
    UnknownPreset(String),
    #[error("render parameter: {0}")]
    Parameter(String),
    #[error("{path}: {message}")]
    Write { path: String, message: String },
}

/// An RGBA8 image (rows top to bottom) and the depth of each pixel along its ray (world
/// units; infinite where nothing was hit).
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    pub width: usize,
    pub height: usize,
    pub rgba: Vec<u8>,
    pub depth: Vec<f32>,
}

impl Rendered {
    pub fn write_png(&self, path: &Path) -> Result<(), RenderError> {
        let err = |message: String| RenderError::Write { path: path.display().to_string(), message };
        let file = std::fs::File::create(path).map_err(|e| err(e.to_string()))?;
        let mut encoder = png::Encoder::new(BufWriter::new(file), self.width as u32, self.height as u32);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| err(e.to_string()))?;
        writer.write_image_data(&self.rgba).map_err(|e| err(e.to_string()))?;
        writer.finish().map_err(|e| err(e.to_string()))
    }

    /// PSNR (dB) of the RGB channels against a reference in 0..1.
    pub fn psnr(&self, reference: &[[f64; 4]]) -> f64 {
        let mse = self
            .rgba
            .chunks_exact(4)
            .zip(reference)
            .map(|(p, r)| (0..3).map(|c| (f64::from(p[c]) - (r[c].clamp(0.0, 1.0) * 255.0)).powi(2)).sum::<f64>())
            .sum::<f64>()
            / (3.0 * reference.len() as f64);
        10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
    }

    /// Mean and max absolute RGB error (0..255 levels) against a reference in 0..1.
    pub fn errors(&self, reference: &[[f64; 4]]) -> (f64, f64) {
        let diffs = self
            .rgba
            .chunks_exact(4)
            .zip(reference)
            .flat_map(|(p, r)| (0..3).map(move |c| (f64::from(p[c]) - r[c].clamp(0.0, 1.0) * 255.0).abs()));
        let (sum, max, n) = diffs.fold((0.0, 0.0f64, 0usize), |(s, m, n), d| (s + d, m.max(d), n + 1));
        (sum / n.max(1) as f64, max)
    }
}
