//! Per-phyxel parameters painted from an image: which parameter, the file, the range its
//! values map onto, and the loading onto the grid.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::error::DpcmError;
use defvol_core::io;

/// A per-phyxel parameter read from an image (PNG, or a one-slice .mha/.nrrd/.nii):
/// intensity 0..1 (PNG) or the raw value (float images) mapped linearly onto `range`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamTexture {
    pub file: PathBuf,
    pub parameter: TexturedParameter,
    /// Values at intensity 0 and 1 (PNG) or the scale of raw values (default [0, 1]).
    #[serde(default = "unit_range")]
    pub range: [f64; 2],
}

fn unit_range() -> [f64; 2] {
    [0.0, 1.0]
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TexturedParameter {
    GroundStiffness,
    GroundDamping,
    /// Initial rest height (a terrain to engrave).
    RestHeight,
}

/// A texture's values on a `width` x `height` grid (nearest sample when sizes differ),
/// mapped onto its range.
pub fn load_texture(texture: &ParamTexture, width: usize, height: usize) -> Result<Vec<f32>, DpcmError> {
    let path = &texture.file;
    let bad = |message: String| DpcmError::Texture { path: path.clone(), message };
    let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
    let (w, h, values): (usize, usize, Vec<f64>) = if is_png {
        let file = std::fs::File::open(path).map_err(|e| bad(e.to_string()))?;
        let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
        decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
        let mut reader = decoder.read_info().map_err(|e| bad(format!("not a readable PNG: {e}")))?;
        let Some(size) = reader.output_buffer_size() else { return Err(bad("PNG too large".into())) };
        let mut buf = vec![0; size];
        let info = reader.next_frame(&mut buf).map_err(|e| bad(format!("not a readable PNG: {e}")))?;
        let channels = info.color_type.samples();
        let (w, h) = (info.width as usize, info.height as usize);
        // Luminance of the first (up to) three channels; alpha ignored.
        let used = channels.min(3);
        let values = (0..w * h)
            .map(|p| {
                let px = &buf[p * channels..p * channels + used];
                px.iter().map(|&c| f64::from(c)).sum::<f64>() / (255.0 * used as f64)
            })
            .collect();
        (w, h, values)
    } else {
        let volume = io::read_volume(path).map_err(|e| bad(e.to_string()))?;
        let [w, h, d] = volume.dims();
        if d != 1 {
            return Err(bad(format!("a parameter texture is one slice; this volume has {d}")));
        }
        (w, h, volume.data().iter().map(|&v| f64::from(v)).collect())
    };
    if w == 0 || h == 0 {
        return Err(bad("empty image".into()));
    }
    let [lo, hi] = texture.range;
    if !(lo.is_finite() && hi.is_finite()) {
        return Err(bad(format!("range [{lo}, {hi}] is not finite")));
    }
    let mapped: Vec<f32> = (0..width * height)
        .map(|i| {
            let (x, y) = (i % width, i / width);
            let (sx, sy) = ((x * w) / width, (y * h) / height);
            (lo + (hi - lo) * values[sy * w + sx]) as f32
        })
        .collect();
    if let Some(i) = mapped.iter().position(|v| !v.is_finite()) {
        return Err(bad(format!("phyxel {i} gets a non-finite value")));
    }
    if texture.parameter != TexturedParameter::RestHeight {
        if let Some(i) = mapped.iter().position(|v| *v < 0.0) {
            return Err(bad(format!("phyxel {i} gets {} < 0 for {:?}", mapped[i], texture.parameter)));
        }
    }
    Ok(mapped)
}
