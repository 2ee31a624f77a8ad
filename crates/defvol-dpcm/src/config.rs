//! What a DPCM surface is made of: its interactions, topology and marker parameters
//! (seed 004, section 7), the presets, the markers a step takes and the scripted paths
//! that drive demos and benchmarks.

use std::path::Path;

use serde::{Deserialize, Serialize};

use defvol_core::io::withhold_found;

use crate::error::DpcmError;
use crate::kernels::{self, Coeffs};
use crate::render;
use crate::texture::{ParamTexture, TexturedParameter};

/// The presets in `config/dpcm/`, compiled in: (name, YAML).
pub const PRESETS: [(&str, &str); 5] = [
    ("water", include_str!("../../../config/dpcm/water.yaml")),
    ("loose_soil", include_str!("../../../config/dpcm/loose_soil.yaml")),
    ("sand", include_str!("../../../config/dpcm/sand.yaml")),
    ("oil_painting", include_str!("../../../config/dpcm/oil_painting.yaml")),
    ("fossil", include_str!("../../../config/dpcm/fossil.yaml")),
];

/// A one-dimensional interaction from the library (seed 004, section 7.2).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum Interaction {
    /// Spring, N/m.
    Elastic {
        stiffness: f64,
    },
    /// Dashpot, N·s/m.
    Viscous {
        damping: f64,
    },
    DampedSpring {
        stiffness: f64,
        damping: f64,
    },
    /// Hysteretic spring (\[CLH96\]): its rest point follows the mass once the stretch exceeds
    /// `threshold` (metres), leaving a permanent mark. Ground links only.
    Plastic {
        stiffness: f64,
        damping: f64,
        threshold: f64,
    },
}

impl Interaction {
    pub(crate) fn stiffness(&self) -> f64 {
        match *self {
            Self::Elastic { stiffness } | Self::DampedSpring { stiffness, .. } | Self::Plastic { stiffness, .. } => {
                stiffness
            }
            Self::Viscous { .. } => 0.0,
        }
    }
    pub(crate) fn damping(&self) -> f64 {
        match *self {
            Self::Viscous { damping } | Self::DampedSpring { damping, .. } | Self::Plastic { damping, .. } => damping,
            Self::Elastic { .. } => 0.0,
        }
    }
    fn validate(&self, name: &str) -> Result<(), DpcmError> {
        let check = |field: &str, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(DpcmError::BadParameter {
                    name: format!("{name}.{field}"),
                    value: v,
                    why: "must be finite and >= 0".into(),
                })
            }
        };
        check("stiffness", self.stiffness())?;
        check("damping", self.damping())?;
        if let Self::Plastic { threshold, .. } = *self {
            if !(threshold.is_finite() && threshold > 0.0) {
                return Err(DpcmError::BadParameter {
                    name: format!("{name}.threshold"),
                    value: threshold,
                    why: "must be finite and > 0".into(),
                });
            }
        }
        Ok(())
    }
}

/// Which neighbours a phyxel is linked to (seed 004, figure 12 and 13).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Topology {
    /// No inter-phyxel links (pure engraving, as the seed's loose soil).
    None,
    Four,
    Eight,
    /// The four diagonal neighbours only: same pattern as `four`, faster propagation.
    Diagonal,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Links {
    pub topology: Topology,
    /// Each link exists with this probability (the stochastic "dynamic oil painting"),
    /// drawn once from `seed`.
    #[serde(default = "one")]
    pub probability: f64,
    #[serde(default)]
    pub seed: u32,
    /// Interaction of the axial links.
    pub axial: Option<Interaction>,
    /// Interaction of the diagonal links (default: the axial one).
    #[serde(default)]
    pub diagonal: Option<Interaction>,
}

fn one() -> f64 {
    1.0
}

/// How a marker pushes the phyxels (seed 004, section 4.2.1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerParams {
    /// N/m.
    pub stiffness: f64,
    /// N·s/m, coupling the phyxels to the marker's own vertical motion while in reach.
    #[serde(default)]
    pub damping: f64,
    /// Radius of influence (metres): the distance threshold.
    pub threshold: f64,
    /// 0: a sphere; towards 1: an ever flatter disc (vertical axis times 1 - flattening).
    #[serde(default)]
    pub flattening: f64,
}

impl MarkerParams {
    /// How far the marker reaches below its centre: its lowest point.
    pub fn reach_below_centre(&self) -> f64 {
        self.threshold * (1.0 - self.flattening)
    }

    pub(crate) fn validate(&self, name: &str) -> Result<(), DpcmError> {
        let bad = |field: &str, v: f64, why: &str| DpcmError::BadParameter {
            name: format!("{name}.{field}"),
            value: v,
            why: why.into(),
        };
        if !(self.stiffness.is_finite() && self.stiffness >= 0.0) {
            return Err(bad("stiffness", self.stiffness, "must be finite and >= 0"));
        }
        if !(self.damping.is_finite() && self.damping >= 0.0) {
            return Err(bad("damping", self.damping, "must be finite and >= 0"));
        }
        if !(self.threshold.is_finite() && self.threshold > 0.0) {
            return Err(bad("threshold", self.threshold, "must be finite and > 0"));
        }
        if !(0.0..1.0).contains(&self.flattening) {
            return Err(bad("flattening", self.flattening, "must be in [0, 1)"));
        }
        Ok(())
    }
}

/// A DPCM run: the grid, its physics and how it is shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DpcmConfig {
    /// What the preset shows (README).
    #[serde(default)]
    pub description: String,
    /// Phyxels along x (columns) and y (rows).
    pub width: usize,
    pub height: usize,
    /// Metres between phyxels.
    pub spacing: f64,
    /// Seconds per step (the seed's Tech).
    pub dt: f64,
    /// kg per phyxel.
    pub mass: f64,
    /// Initial Z, metres (the seed initialises Z to the ground link's rest length).
    #[serde(default)]
    pub rest_height: f64,
    pub ground: Interaction,
    pub links: Links,
    pub marker: MarkerParams,
    #[serde(default)]
    pub textures: Vec<ParamTexture>,
    #[serde(default)]
    pub render: render::RenderConfig,
    /// The scripted markers used when no other source is given.
    #[serde(default)]
    pub script: Script,
}

impl DpcmConfig {
    pub fn preset(name: &str) -> Result<Self, DpcmError> {
        let Some((_, text)) = PRESETS.iter().find(|(n, _)| *n == name) else {
            return Err(DpcmError::UnknownPreset(name.to_owned()));
        };
        Self::from_yaml(text, &format!("preset {name}"))
    }

    pub fn from_yaml(text: &str, source_name: &str) -> Result<Self, DpcmError> {
        serde_yaml_ng::from_str(text).map_err(|e| DpcmError::Parse {
            source_name: source_name.to_owned(),
            message: withhold_found(&e.to_string()),
        })
    }

    pub fn load(path: &Path) -> Result<Self, DpcmError> {
        let text = std::fs::read_to_string(path).map_err(|source| DpcmError::File { path: path.to_owned(), source })?;
        Self::from_yaml(&text, &path.display().to_string())
    }

    /// Checks every parameter and the explicit step's stability; the per-step coefficients.
    pub fn coeffs(&self) -> Result<Coeffs, DpcmError> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(DpcmError::BadParameter { name: name.into(), value: v, why: "must be finite and > 0".into() })
            }
        };
        positive("dt", self.dt)?;
        positive("mass", self.mass)?;
        positive("spacing", self.spacing)?;
        for (name, n) in [("width", self.width), ("height", self.height)] {
            if n < 3 {
                return Err(DpcmError::BadParameter {
                    name: name.into(),
                    value: n as f64,
                    why: "the grid needs at least 3 phyxels a side".into(),
                });
            }
        }
        if self.width.checked_mul(self.height).is_none_or(|n| n > u32::MAX as usize / 4) {
            return Err(DpcmError::BadParameter {
                name: "width x height".into(),
                value: (self.width as f64) * (self.height as f64),
                why: "more phyxels than a u32 index allows".into(),
            });
        }
        if !self.rest_height.is_finite() {
            return Err(DpcmError::BadParameter {
                name: "rest_height".into(),
                value: self.rest_height,
                why: "must be finite".into(),
            });
        }
        if !(0.0..=1.0).contains(&self.links.probability) {
            return Err(DpcmError::BadParameter {
                name: "links.probability".into(),
                value: self.links.probability,
                why: "must be in [0, 1]".into(),
            });
        }
        self.ground.validate("ground")?;
        self.marker.validate("marker")?;
        let axial = self.links.axial.unwrap_or(Interaction::Elastic { stiffness: 0.0 });
        let diagonal = self.links.diagonal.unwrap_or(axial);
        for (name, link) in [("links.axial", axial), ("links.diagonal", diagonal)] {
            link.validate(name)?;
            if matches!(link, Interaction::Plastic { .. }) {
                return Err(DpcmError::BadParameter {
                    name: name.into(),
                    value: link.stiffness(),
                    why: "plastic links between phyxels are not in the library (they need a state per link); make the ground link plastic".into(),
                });
            }
        }
        if self.links.topology != Topology::None && self.links.axial.is_none() {
            return Err(DpcmError::BadParameter {
                name: "links.axial".into(),
                value: f64::NAN,
                why: format!("topology {:?} needs an interaction", self.links.topology),
            });
        }
        let (has_axial, has_diagonal) = match self.links.topology {
            Topology::None => (false, false),
            Topology::Four => (true, false),
            Topology::Eight => (true, true),
            Topology::Diagonal => (false, true),
        };
        let (h, m) = (self.dt, self.mass);
        let ground_k = self.ground.stiffness() * self.texture_max(TexturedParameter::GroundStiffness);
        let ground_c = self.ground.damping() * self.texture_max(TexturedParameter::GroundDamping);
        // Largest eigenvalue of the lattice's link matrix (a Fourier mode at a corner of the
        // Brillouin zone); a stochastic or bordered grid is a subgraph, whose eigenvalues are
        // no larger.
        let lattice_max = |axial: f64, diagonal: f64| match (has_axial, has_diagonal) {
            (false, false) => 0.0,
            (true, false) => 8.0 * axial,
            (false, true) => 8.0 * diagonal,
            (true, true) => f64::max(8.0 * axial, 4.0 * axial + 8.0 * diagonal),
        };
        let k_sum = ground_k + lattice_max(axial.stiffness(), diagonal.stiffness()) + self.marker.stiffness;
        let c_sum = ground_c + lattice_max(axial.damping(), diagonal.damping()) + self.marker.damping;
        let value = h * h / m * k_sum + 2.0 * h / m * c_sum;
        if value >= 4.0 {
            // Largest h with h²·K/m + 2h·C/m < 4.
            let (a, b) = (k_sum / m, 2.0 * c_sum / m);
            let dt_max = if a > 0.0 { (-b + (b * b + 16.0 * a).sqrt()) / (2.0 * a) } else { 4.0 / b };
            return Err(DpcmError::Unstable { value, dt_max });
        }
        let threshold = match self.ground {
            Interaction::Plastic { threshold, .. } => threshold as f32,
            _ => -1.0,
        };
        let keep = (self.links.probability * f64::from(1u32 << 24)).round() as u32;
        let (axial_a, axial_b) = ((axial.stiffness() * h * h / m) as f32, (axial.damping() * h / m) as f32);
        let (diag_a, diag_b) = ((diagonal.stiffness() * h * h / m) as f32, (diagonal.damping() * h / m) as f32);
        Ok(Coeffs {
            ground_a: (self.ground.stiffness() * h * h / m) as f32,
            ground_b: (self.ground.damping() * h / m) as f32,
            axial_a,
            axial_b,
            axial_ab: axial_a + axial_b,
            diag_a,
            diag_b,
            diag_ab: diag_a + diag_b,
            plastic_threshold: threshold,
            link_keep: keep,
            link_seed: kernels::hash32(self.links.seed ^ 0x9e37_79b9),
            has_axial: u32::from(has_axial),
            has_diagonal: u32::from(has_diagonal),
            _pad: [0; 3],
        })
    }

    /// The largest multiplier a texture puts on `parameter` (1 without one).
    fn texture_max(&self, parameter: TexturedParameter) -> f64 {
        self.textures
            .iter()
            .filter(|t| t.parameter == parameter)
            .map(|t| t.range[0].max(t.range[1]).max(0.0))
            .fold(1.0, f64::max)
    }
}

/// A marker at one step, in grid coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Marker {
    /// Stable identity across steps (the marker's velocity comes from its last height).
    pub id: u32,
    /// Column and row, in phyxels (fractional).
    pub col: f64,
    pub row: f64,
    /// Height of the marker's centre above the fixed plane, metres.
    pub height: f64,
    /// Its own parameters; the configuration's when `None`.
    pub params: Option<MarkerParams>,
}

/// Scripted marker paths, for demos, pictures and benchmarks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Script {
    pub markers: usize,
    pub pattern: Pattern,
    /// Metres per second along the path.
    pub speed: f64,
    /// How far the marker's lowest point goes below the rest height (metres).
    pub depth: f64,
    /// Markers leave (lift off the surface) after this many seconds.
    pub leave_after: Option<f64>,
}

impl Default for Script {
    fn default() -> Self {
        Self { markers: 1, pattern: Pattern::Lines, speed: 0.05, depth: 0.001, leave_after: None }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pattern {
    /// Markers on evenly spaced rows crossing the grid from left to right (tracks, boats).
    Lines,
    /// Markers evenly spaced on a circle, going round it.
    Circle,
    /// Each marker on its own Lissajous path over the whole grid (many markers at once).
    Wander,
}

impl Script {
    /// The height of a marker centre that reaches `depth` below the rest height.
    pub fn pressing_height(&self, config: &DpcmConfig) -> f64 {
        config.rest_height + config.marker.reach_below_centre() - self.depth
    }

    /// The markers at time `t` (seconds).
    pub fn markers_at(&self, config: &DpcmConfig, t: f64) -> Vec<Marker> {
        if self.leave_after.is_some_and(|leave| t >= leave) {
            return Vec::new();
        }
        let (w, h) = ((config.width - 1) as f64, (config.height - 1) as f64);
        let height = self.pressing_height(config);
        let travelled = self.speed * t / config.spacing;
        let k = self.markers.max(1);
        (0..k)
            .map(|i| {
                let f = (i as f64 + 0.5) / k as f64;
                let (col, row) = match self.pattern {
                    Pattern::Lines => {
                        let margin = 0.1 * w;
                        (margin + travelled % (w - 2.0 * margin).max(1.0), 0.15 * h + 0.7 * h * f)
                    }
                    Pattern::Circle => {
                        let radius = 0.3 * w.min(h);
                        let angle = std::f64::consts::TAU * f + travelled / radius;
                        (0.5 * w + radius * angle.cos(), 0.5 * h + radius * angle.sin())
                    }
                    Pattern::Wander => {
                        let phase = 2.399_963 * i as f64; // golden angle: spread without pattern
                        let s = travelled / (w + h);
                        (
                            0.5 * w + 0.45 * w * (s * 1.3 + phase).sin(),
                            0.5 * h + 0.45 * h * (s * 1.7 + 1.3 * phase).cos(),
                        )
                    }
                };
                Marker { id: i as u32, col, row, height, params: None }
            })
            .collect()
    }
}
