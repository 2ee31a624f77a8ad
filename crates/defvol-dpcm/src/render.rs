//! Phyxels into pixels (seed 004, section 4.2.3): colour map, bump map, displacement mesh,
//! and the height as data. Parameter textures are read here too.

use std::io::BufWriter;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::DpcmError;
use defvol_core::io;
use defvol_core::volume::Volume;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColorMap {
    Viridis,
    Magma,
    Inferno,
    Plasma,
    Turbo,
    Cividis,
    Greys,
    /// Diverging: dents red, bumps blue.
    #[serde(alias = "red-blue")]
    RedBlue,
    /// Diverging, earthy: for soil and sand.
    #[serde(alias = "brown-green")]
    BrownGreen,
}

impl ColorMap {
    fn gradient(self) -> colorous::Gradient {
        match self {
            Self::Viridis => colorous::VIRIDIS,
            Self::Magma => colorous::MAGMA,
            Self::Inferno => colorous::INFERNO,
            Self::Plasma => colorous::PLASMA,
            Self::Turbo => colorous::TURBO,
            Self::Cividis => colorous::CIVIDIS,
            Self::Greys => colorous::GREYS,
            Self::RedBlue => colorous::RED_BLUE,
            Self::BrownGreen => colorous::BROWN_GREEN,
        }
    }
}

/// How a preset is shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderConfig {
    pub colormap: ColorMap,
    /// Displacement (metres) at the two ends of the map; symmetric about 0 at the largest
    /// |displacement| when absent.
    pub range: Option<[f64; 2]>,
    /// Direction towards the light (grid frame; normalised).
    pub light: [f64; 3],
    /// Height exaggeration of the bump map's normals.
    pub bump_scale: f64,
    pub ambient: f64,
}

impl Default for RenderConfig {
    fn default() -> Self {
        Self { colormap: ColorMap::RedBlue, range: None, light: [-1.0, -1.0, 2.0], bump_scale: 1.0, ambient: 0.25 }
    }
}

/// An RGB8 image, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl Image {
    pub fn write_png(&self, path: &Path) -> Result<(), DpcmError> {
        let file_err = |source| DpcmError::File { path: path.to_owned(), source };
        let file = std::fs::File::create(path).map_err(file_err)?;
        let mut encoder = png::Encoder::new(BufWriter::new(file), self.width as u32, self.height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let png_err = |e: png::EncodingError| DpcmError::Texture {
            path: path.to_owned(),
            message: format!("cannot write PNG: {e}"),
        };
        let mut writer = encoder.write_header().map_err(png_err)?;
        writer.write_image_data(&self.rgb).map_err(png_err)?;
        writer.finish().map_err(png_err)
    }
}

/// The colour-map range: the configured one, or symmetric about 0.
fn range(config: &RenderConfig, displacement: &[f32]) -> (f32, f32) {
    if let Some([lo, hi]) = config.range {
        return (lo as f32, hi as f32);
    }
    let peak = displacement.iter().fold(0.0f32, |m, d| m.max(d.abs())).max(f32::MIN_POSITIVE);
    (-peak, peak)
}

fn colour(gradient: &colorous::Gradient, lo: f32, hi: f32, d: f32) -> [u8; 3] {
    let t = if hi > lo { ((d - lo) / (hi - lo)).clamp(0.0, 1.0) } else { 0.5 };
    let c = gradient.eval_continuous(f64::from(t));
    [c.r, c.g, c.b]
}

/// Colour map of the displacement (the seed's pinscreen-like rendering).
pub fn colour_map(displacement: &[f32], width: usize, height: usize, config: &RenderConfig) -> Image {
    let (lo, hi) = range(config, displacement);
    let gradient = config.colormap.gradient();
    let rgb = displacement.par_iter().flat_map_iter(|&d| colour(&gradient, lo, hi, d)).collect();
    Image { width, height, rgb }
}

/// Bump map: normals from central differences of the heights, Lambert-lit, over the
/// colour map.
pub fn bump_map(displacement: &[f32], width: usize, height: usize, spacing: f64, config: &RenderConfig) -> Image {
    let (lo, hi) = range(config, displacement);
    let gradient = config.colormap.gradient();
    let light = Vector3::from(config.light).try_normalize(0.0).unwrap_or_else(Vector3::z);
    let scale = config.bump_scale / (2.0 * spacing);
    let at = |x: usize, y: usize| f64::from(displacement[y * width + x]);
    let rgb = (0..width * height)
        .into_par_iter()
        .flat_map_iter(|i| {
            let (x, y) = (i % width, i / width);
            let dzdx = (at((x + 1).min(width - 1), y) - at(x.saturating_sub(1), y)) * scale;
            let dzdy = (at(x, (y + 1).min(height - 1)) - at(x, y.saturating_sub(1))) * scale;
            let normal = Vector3::new(-dzdx, -dzdy, 1.0).normalize();
            let shade = config.ambient + (1.0 - config.ambient) * normal.dot(&light).max(0.0);
            colour(&gradient, lo, hi, displacement[i]).map(|c| (f64::from(c) * shade).round().clamp(0.0, 255.0) as u8)
        })
        .collect();
    Image { width, height, rgb }
}

/// A height field as triangles (grid frame, metres): every `stride`-th phyxel a vertex.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightMesh {
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    /// The displacement at each vertex.
    pub scalars: Vec<f32>,
}

pub fn displacement_mesh(
    heights: &[f32],
    displacement: &[f32],
    width: usize,
    height: usize,
    spacing: f64,
    stride: usize,
) -> HeightMesh {
    let stride = stride.max(1);
    let xs: Vec<usize> = (0..width).step_by(stride).collect();
    let ys: Vec<usize> = (0..height).step_by(stride).collect();
    let mut positions = Vec::with_capacity(xs.len() * ys.len());
    let mut scalars = Vec::with_capacity(positions.capacity());
    for &y in &ys {
        for &x in &xs {
            let i = y * width + x;
            positions.push([(x as f64 * spacing) as f32, (y as f64 * spacing) as f32, heights[i]]);
            scalars.push(displacement[i]);
        }
    }
    let nx = xs.len() as u32;
    let mut triangles = Vec::with_capacity(2 * xs.len() * ys.len());
    for j in 0..ys.len().saturating_sub(1) as u32 {
        for i in 0..nx - 1 {
            let a = j * nx + i;
            // Counter-clockwise seen from +z: normals point up.
            triangles.push([a, a + 1, a + nx + 1]);
            triangles.push([a, a + nx + 1, a + nx]);
        }
    }
    HeightMesh { positions, triangles, scalars }
}

/// The height as a float image (one-slice volume; `.mha`, `.nrrd`, `.nii`), in metres with
/// the phyxel spacing.
pub fn write_height(path: &Path, values: &[f32], width: usize, height: usize, spacing: f64) -> Result<(), DpcmError> {
    let volume = Volume::new(
        [width, height, 1],
        [spacing; 3],
        [0.0; 3],
        Matrix3::identity(),
        values.to_vec(),
        &path.display().to_string(),
    )
    .map_err(|e| DpcmError::Texture { path: path.to_owned(), message: e.to_string() })?;
    io::write_volume(path, &volume).map_err(|e| DpcmError::Texture { path: path.to_owned(), message: e.to_string() })
}
