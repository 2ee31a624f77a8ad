//! Scene descriptions (YAML): what to load or generate, the material, the solver and the
//! tools. The default scene is `config/default_scene.yaml`, compiled in.

mod confined;
pub mod descriptors;
pub mod field_path;
mod inherit;

pub use confined::{
    check_scene_size, named_file, read_scene_text, AllowedDirs, Expect, ALLOWED_DIRS_PARAMETER, MAX_SCENE_BYTES,
};

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Isometry3, Vector3};
use serde::{Deserialize, Serialize};

use crate::backend::{Backend, BackendChoice, BackendError};
use crate::io::{self, IoError};
use crate::mesh::generate::{self, CellSplit};
use crate::mesh::{MeshError, TetMesh};
use crate::solver::{
    ContactModel, Coupling, FixedNodes, Friction, MassSpringModel, Material, RotationalCoupling, SolverError,
    SolverParams, Tool, ToolShape,
};
use crate::volume::{phantom, Volume, VolumeError};

pub const DEFAULT_SCENE: &str = include_str!("../../config/default_scene.yaml");

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    #[error("{path}: {message}")]
    Parse { path: String, message: String },
    #[error(transparent)]
    Io(#[from] IoError),
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    Volume(#[from] VolumeError),
    #[error(transparent)]
    Solver(#[from] SolverError),
    #[error("scene: {0}")]
    Invalid(String),
    #[error("{path}: {why}")]
    Refused { path: String, why: String },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum MeshSource {
    /// A mesh file. Its nodes are in the unit the file records (defvol's own VTK files do),
    /// else in the scene's file units; `scale` (world units per file unit) overrides both.
    File {
        path: PathBuf,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        scale: Option<f64>,
    },
    /// A lattice of about `target_tets` tets embedding the volume's box.
    VolumeLattice {
        target_tets: usize,
        split: CellSplit,
    },
    /// A lattice over an explicit box (world units).
    Lattice {
        min: [f64; 3],
        max: [f64; 3],
        target_tets: usize,
        split: CellSplit,
    },
    /// The seed's 80-tet bar of the given length, along x from the origin.
    Bar {
        length: f64,
    },
    Ellipsoid {
        centre: [f64; 3],
        radii: [f64; 3],
        cells_per_axis: usize,
    },
}

/// A straight tool path: `from` to `to` over `duration` seconds, then held.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolPath {
    pub from: [f64; 3],
    pub to: [f64; 3],
    pub duration: f64,
}

impl ToolPath {
    pub fn position(&self, t: f64) -> Vector3<f64> {
        let s = if self.duration > 0.0 { (t / self.duration).clamp(0.0, 1.0) } else { 1.0 };
        Vector3::from(self.from) * (1.0 - s) + Vector3::from(self.to) * s
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolConfig {
    pub name: String,
    pub shape: ToolShape,
    pub contact_stiffness: f64,
    pub spread_radius: f64,
    /// `surface` (default: faces, edges and nodes, for tools of any thickness) or `nodes`
    /// (every node inside the shape; what the GPU solver does).
    #[serde(default)]
    pub contact: ContactModel,
    /// A virtual coupling to the device: the simulated tool follows the pose through a
    /// spring-damper and the device feels it (haptic rendering).
    #[serde(default)]
    pub coupling: Option<Coupling>,
    /// Coulomb friction against the surface (`{static, kinetic, stick_speed}`; surface
    /// contact): none, frictionless.
    #[serde(default)]
    pub friction: Option<Friction>,
    /// With a `coupling`, a torsional one too (`{stiffness, damping, inertia, max_torque}`):
    /// the simulated tool turns, and the device feels the torque that holds it.
    #[serde(default)]
    pub rotational_coupling: Option<RotationalCoupling>,
    #[serde(default)]
    pub path: Option<ToolPath>,
    /// Input topics (relative to the node's namespace); `tool_pose` and `tool_wrench` for
    /// the first tool, `<name>/tool_pose` and `<name>/tool_wrench` for the others.
    #[serde(default)]
    pub pose_topic: Option<String>,
    #[serde(default)]
    pub wrench_topic: Option<String>,
    /// Output topic of the reaction on this tool: `tool_feedback` for the first tool,
    /// `<name>/tool_feedback` for the others.
    #[serde(default)]
    pub feedback_topic: Option<String>,
}

/// Which stages a scene runs; a stage left out is never initialised.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Stages {
    pub solver: bool,
    pub warp: bool,
    pub dpcm: bool,
    pub raycast: bool,
}

impl Default for Stages {
    fn default() -> Self {
        Self { solver: true, warp: false, dpcm: false, raycast: false }
    }
}

/// How tool inputs are checked beyond finiteness, frame and magnitude.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InputsConfig {
    /// Seconds a pose or wrench may be stamped before it arrives (0: any age, for a device
    /// whose clock is not synchronised with this host's).
    pub max_age: f64,
}

impl Default for InputsConfig {
    fn default() -> Self {
        Self { max_age: 0.5 }
    }
}

/// The grid-warp stage: the volume carried through the deformed mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WarpStageConfig {
    /// Most warps per second of simulated time.
    pub rate_hz: f64,
    /// Nodes that moved less than this (metres) from where the warp last placed them stay
    /// there for the warp, and their tets alone; slow drift is caught once it adds up.
    pub tolerance: f64,
    /// The iceoryx2 service carrying the volumes.
    pub service: String,
}

impl Default for WarpStageConfig {
    fn default() -> Self {
        Self { rate_hz: 10.0, tolerance: 1e-5, service: "defvol/warped_volume".into() }
    }
}

/// The DPCM surface: a phyxel grid lying on a plane of the scene, engraved by the tools.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DpcmStageConfig {
    /// A preset name (`config/dpcm/`) or a DPCM YAML file.
    pub preset: String,
    /// Phyxels along x and y (the preset's size when absent).
    pub size: Option<[usize; 2]>,
    /// Metres between phyxels (the preset's when absent).
    pub spacing: Option<f64>,
    /// World position of phyxel (0, 0); the grid's x and y run along the world's.
    pub origin: [f64; 3],
    /// Most images per second of simulated time.
    pub rate_hz: f64,
    /// Steps per GPU submission (the DPCM steps per solver step when absent).
    pub batch: Option<usize>,
}

impl Default for DpcmStageConfig {
    fn default() -> Self {
        Self { preset: "water".into(), size: None, spacing: None, origin: [0.0; 3], rate_hz: 10.0, batch: None }
    }
}

/// What the raycast camera looks at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraShows {
    /// The source volume as the warp deforms it (as it is when the warp stage is off).
    #[default]
    Volume,
    /// The deformed tetrahedral mesh raycast directly (seed 000, section 5), its node values
    /// sampled from the source at rest: the picture needs no warp.
    Mesh,
    /// The source volume at full resolution seen through the deformed mesh (each sample
    /// mapped back to rest through its tet, seed 002): the detail of `volume` with no warp.
    Source,
}

impl Scene {
    /// The run's backend: the command line's over the scene's own, resolved once.
    pub fn backend(&self, args: &BackendArgs) -> Result<Backend, BackendError> {
        Backend::choose(args.backend.unwrap_or(self.backend), args.allow_software_gpu || self.allow_software_gpu)
    }
}

/// The command line's backend options, flattened into every command that runs a stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::Args)]
pub struct BackendArgs {
    /// Where the stages run: auto (the GPU when a hardware adapter exists, else the CPU),
    /// cpu, or gpu (an error without a usable adapter). Default: the scene's `backend`;
    /// auto for a command without a scene; cpu for `replay`, where it is deterministic.
    #[arg(long, value_parser = backend_choice_parser())]
    pub backend: Option<BackendChoice>,
    /// Let a software adapter (lavapipe, llvmpipe) count as a GPU: correctness, not speed.
    #[arg(long)]
    pub allow_software_gpu: bool,
}

impl BackendArgs {
    /// The backend of a command without a scene: `--backend`, else `default`.
    pub fn choose_or(&self, default: BackendChoice) -> Result<Backend, BackendError> {
        Backend::choose(self.backend.unwrap_or(default), self.allow_software_gpu)
    }
}

/// `auto | cpu | gpu`, listed by `--help`.
fn backend_choice_parser() -> impl clap::builder::TypedValueParser<Value = BackendChoice> {
    use clap::builder::TypedValueParser as _;
    clap::builder::PossibleValuesParser::new(["auto", "cpu", "gpu"]).try_map(|name| name.parse::<BackendChoice>())
}

/// The raycast camera and what it shows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// World positions (metres).
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y_deg: f64,
    pub width: usize,
    pub height: usize,
    /// Transfer-function preset: ct_soft_tissue, ct_bone or mri.
    pub transfer_function: String,
    pub shows: CameraShows,
    /// Ray step in the volume's file units (for `shows: mesh`, the longest piece of a tet's
    /// segment one pre-integrated lookup covers; for `volume` and `source`, the sample
    /// spacing, best near the source's voxel spacing).
    pub step: f64,
    /// Most frames per second of simulated time.
    pub rate_hz: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            eye: [0.0, -0.45, 0.25],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 0.0, 1.0],
            fov_y_deg: 35.0,
            width: 320,
            height: 240,
            transfer_function: "ct_soft_tissue".into(),
            shows: CameraShows::Volume,
            step: 1.0,
            rate_hz: 10.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// "phantom", a volume file, or a DICOM folder or file.
    pub volume: String,
    /// With DICOM: the series to read (its SeriesInstanceUID); the largest when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume_series: Option<String>,
    /// World units per file unit (0.001: millimetre files, metre world).
    pub file_to_world: f64,
    pub mesh: MeshSource,
    pub material: Material,
    pub density: f64,
    pub fixed: Option<FixedNodes>,
    pub solver: SolverParams,
    #[serde(default)]
    pub tools: Vec<ToolConfig>,
    /// The world frame: poses must be given in it (or with an empty frame_id).
    #[serde(default = "default_frame")]
    pub frame_id: String,
    #[serde(default)]
    pub stages: Stages,
    #[serde(default)]
    pub inputs: InputsConfig,
    #[serde(default)]
    pub warp: WarpStageConfig,
    #[serde(default)]
    pub dpcm: DpcmStageConfig,
    #[serde(default)]
    pub camera: CameraConfig,
    /// Where every stage runs: `auto` (the GPU when a usable one exists), `cpu` or `gpu`.
    /// Chosen once per run (a reloaded scene keeps the run's).
    #[serde(default)]
    pub backend: BackendChoice,
    /// Let a software adapter (lavapipe, llvmpipe) count as a GPU (tests, CI).
    #[serde(default)]
    pub allow_software_gpu: bool,
}

fn default_frame() -> String {
    "world".into()
}

impl ToolConfig {
    /// The solver's tool of this configuration, at the origin.
    pub fn tool(&self) -> Tool {
        let mut tool = Tool::new(self.shape, self.contact_stiffness);
        tool.spread_radius = self.spread_radius;
        tool.contact = self.contact;
        tool.coupling = self.coupling;
        tool.friction = self.friction;
        tool.rotational_coupling = self.rotational_coupling;
        tool
    }

    /// Why this tool's surface contact is too soft for its coupling, if it is: pulled with
    /// the coupling's largest force, the penalty lets the tool in by max_force / k_c; past
    /// its radius the tool's centre is inside the body, where one face alone holds it and a
    /// held tool may not come to rest.
    pub fn too_soft_for_its_coupling(&self) -> Option<String> {
        let coupling = self.coupling.filter(|_| self.contact == ContactModel::Surface)?;
        let (depth, radius) = (coupling.max_force / self.contact_stiffness, self.shape.radius());
        (depth > radius).then(|| {
            format!(
                "tool `{}`: pulled with the coupling's max_force ({} N), a contact_stiffness of {} N/m lets it \
                 {:.2} mm in, past its {:.2} mm radius; raise contact_stiffness to {:.0} N/m or more",
                self.name,
                coupling.max_force,
                self.contact_stiffness,
                depth * 1e3,
                radius * 1e3,
                coupling.max_force / radius
            )
        })
    }

    /// The pose topic of the tool at `index`.
    pub fn pose_topic(&self, index: usize) -> String {
        self.pose_topic.clone().unwrap_or_else(|| {
            if index == 0 {
                "tool_pose".into()
            } else {
                format!("{}/tool_pose", self.name)
            }
        })
    }
    pub fn wrench_topic(&self, index: usize) -> String {
        self.wrench_topic.clone().unwrap_or_else(|| {
            if index == 0 {
                "tool_wrench".into()
            } else {
                format!("{}/tool_wrench", self.name)
            }
        })
    }
    pub fn feedback_topic(&self, index: usize) -> String {
        self.feedback_topic.clone().unwrap_or_else(|| {
            if index == 0 {
                "tool_feedback".into()
            } else {
                format!("{}/tool_feedback", self.name)
            }
        })
    }
}

/// What a new scene changes of a running one, by what it takes to apply it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SceneChange {
    /// Fields that change the mesh, the material or the solver's system: the simulation is
    /// rebuilt and restarts from rest.
    pub physics: Vec<&'static str>,
    /// The inputs' checks (`frame_id`, `inputs`): the force loop takes them as it runs.
    pub checks: bool,
    /// Stages after the solver (`stages` but the solver's, `warp`, `dpcm`, `camera`):
    /// rebuilt alone, the simulation running on.
    pub outputs: bool,
    /// Among them the warp (`stages.warp`, `warp`): its shared volumes change hands.
    pub warp: bool,
}

impl Scene {
    /// What `self` changes of `running` (`backend` and `allow_software_gpu` are the run's,
    /// chosen once: a new scene keeps them).
    pub fn change_from(&self, running: &Scene) -> SceneChange {
        let (a, b) = (self, running);
        let physics = [
            ("volume", a.volume != b.volume || a.volume_series != b.volume_series),
            ("file_to_world", a.file_to_world != b.file_to_world),
            ("mesh", a.mesh != b.mesh),
            ("material", a.material != b.material),
            ("density", a.density != b.density),
            ("fixed", a.fixed != b.fixed),
            ("solver", a.solver != b.solver),
            ("tools", a.tools != b.tools),
            ("stages.solver", a.stages.solver != b.stages.solver),
        ];
        let outputs = Stages { solver: b.stages.solver, ..a.stages } != b.stages
            || a.warp != b.warp
            || a.dpcm != b.dpcm
            || a.camera != b.camera;
        SceneChange {
            physics: physics.into_iter().filter(|(_, changed)| *changed).map(|(name, _)| name).collect(),
            checks: a.frame_id != b.frame_id || a.inputs != b.inputs,
            outputs,
            warp: a.stages.warp != b.stages.warp || a.warp != b.warp,
        }
    }
}

/// Everything a run needs, loaded and validated.
pub struct LoadedScene {
    pub scene: Scene,
    /// The volume, in file units.
    pub volume: Arc<Volume>,
    /// The mesh, in world units.
    pub mesh: TetMesh,
    pub model: MassSpringModel,
}

impl Scene {
    pub fn default_scene() -> Result<Self, SceneError> {
        Self::parse(DEFAULT_SCENE, "embedded default scene")
    }

    /// A scene from YAML text, every field it omits the embedded scene's (`mesh: FILE` a mesh
    /// file); `origin` names it in errors, which name the field at fault and its line.
    pub fn parse(text: &str, origin: &str) -> Result<Self, SceneError> {
        let refused = |message| SceneError::Parse { path: origin.to_owned(), message };
        let tree: serde_yaml_ng::Value =
            serde_yaml_ng::from_str(text).map_err(|e| refused(crate::io::withhold_found(&e.to_string())))?;
        let base = serde_yaml_ng::from_str(DEFAULT_SCENE).map_err(|e| refused(e.to_string()))?;
        let whole = serde_yaml_ng::to_string(&inherit::inherit(tree, &base)).map_err(|e| refused(e.to_string()))?;
        field_path::parse(&whole, DEFAULT_SCENE, Some(text)).map_err(refused)
    }

    /// A scene file; the files it names by relative paths lie beside it.
    pub fn from_file(path: &Path) -> Result<Self, SceneError> {
        let text = read_scene_text(path)?;
        let mut scene = Self::parse(&text, &path.display().to_string())?;
        scene.resolve_against(path.parent().unwrap_or(Path::new("")));
        Ok(scene)
    }

    /// The scene read and built: its volume, its mesh in world units, its model.
    pub fn load(self) -> Result<LoadedScene, SceneError> {
        self.check()?;
        let volume = if self.volume == "phantom" {
            phantom::phantom(phantom::DEFAULT_DIMS, 1.0)?
        } else {
            io::read_volume_series(Path::new(&self.volume), self.volume_series.as_deref())?
        };
        self.build_on(Arc::new(volume))
    }

    /// The scene built on `volume`, already read (a reset, or a change that keeps the volume).
    pub fn load_on(self, volume: Arc<Volume>) -> Result<LoadedScene, SceneError> {
        self.check()?;
        self.build_on(volume)
    }

    /// The mesh and model of a checked scene on `volume`.
    fn build_on(self, volume: Arc<Volume>) -> Result<LoadedScene, SceneError> {
        let scale = self.file_to_world;
        let mesh = match &self.mesh {
            MeshSource::File { path, scale: chosen } => read_world_mesh(path, *chosen, scale)?,
            MeshSource::VolumeLattice { target_tets, split } => {
                let (lo, hi) = volume.bounds();
                generate::lattice_for_box(lo * scale, hi * scale, *target_tets, *split)?
            }
            MeshSource::Lattice { min, max, target_tets, split } => {
                generate::lattice_for_box(Vector3::from(*min), Vector3::from(*max), *target_tets, *split)?
            }
            MeshSource::Bar { length } => generate::bar(*length)?,
            MeshSource::Ellipsoid { centre, radii, cells_per_axis } => {
                generate::ellipsoid(Vector3::from(*centre), Vector3::from(*radii), *cells_per_axis)?
            }
        };
        let fixed = match &self.fixed {
            Some(f) => f.select(mesh.nodes())?,
            None => vec![false; mesh.nodes().len()],
        };
        if !fixed.contains(&true) {
            let chosen = self.fixed.as_ref().map_or("no `fixed` is given".to_owned(), |f| format!("`fixed` ({f})"));
            tracing::warn!(
                "no node is held: {chosen} selects none of the mesh's {} nodes, so gravity will carry the organ \
                 away (`fixed: {{kind: lowest}}` rests it on its lowest layer)",
                fixed.len()
            );
        }
        let sample = |p: &Vector3<f64>| volume.sample_world(p / scale);
        let model = MassSpringModel::new(&mesh, &self.material, self.density, &fixed, Some(&sample))?;
        Ok(LoadedScene { scene: self, volume, mesh, model })
    }

    /// What must hold before anything is read or built: every field within the range its
    /// parameter has (one set of ranges for scene files, `-p` and `ros2 param set`), each
    /// one outside named by its path.
    fn check(&self) -> Result<(), SceneError> {
        let outside = descriptors::out_of_range(self);
        if !outside.is_empty() {
            return Err(SceneError::Invalid(outside.join("; ")));
        }
        for tool in self.tools.iter().filter(|tool| tool.shape.radius() > PLAUSIBLE_TOOL_RADIUS) {
            tracing::warn!(
                "tool {} has a radius of {} m, more than any surgical tool's: is it in metres? (a 2 mm \
                 probe is radius: 0.002)",
                tool.name,
                tool.shape.radius()
            );
        }
        self.solver.validate()?;
        for why in self.tools.iter().filter_map(ToolConfig::too_soft_for_its_coupling) {
            tracing::warn!("{why}");
        }
        Ok(())
    }
}

/// The largest tool radius (m) taken without a word: an instrument's tip, a finger.
const PLAUSIBLE_TOOL_RADIUS: f64 = 0.05;

/// A mesh file in world metres: scaled by `chosen`, else by the unit the file records, else
/// by the scene's `file_to_world`; the log says which, and warns of a size no organ has.
fn read_world_mesh(path: &Path, chosen: Option<f64>, file_to_world: f64) -> Result<TetMesh, SceneError> {
    if let Some(scale) = chosen.filter(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(SceneError::Invalid(format!("mesh scale {scale} must be finite and > 0")));
    }
    let read = io::read_mesh_with_metadata(path)?;
    let why = match (chosen, read.metres_per_unit) {
        (Some(_), _) => "as asked".to_owned(),
        (None, Some(unit)) => format!("the file records {unit} m per unit"),
        (None, None) => format!("the scene's file_to_world {file_to_world}"),
    };
    let (mesh, scale) = read.into_scaled(1.0, chosen, file_to_world);
    let (lo, hi) = crate::mesh::bounds(mesh.nodes());
    let size = (hi - lo).max();
    tracing::info!("mesh {}: x{scale} to metres ({why}): {size:.4} m across", path.display());
    if !(0.001..=10.0).contains(&size) {
        tracing::warn!(
            "mesh {} is {size:.4} m across: is its unit right? (--mesh-scale, or `scale:` in the scene)",
            path.display()
        );
    }
    Ok(mesh)
}

impl LoadedScene {
    /// The scene's tools at time `t` (scripted paths applied).
    pub fn tools_at(&self, t: f64) -> Vec<Tool> {
        self.scene
            .tools
            .iter()
            .map(|c| {
                let mut tool = c.tool();
                if let Some(path) = &c.path {
                    tool.world_from_tool =
                        Isometry3::translation(path.position(t).x, path.position(t).y, path.position(t).z);
                }
                tool
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_change_is_sorted_by_what_it_takes_to_apply() {
        let running = Scene::default_scene().unwrap();
        let change = |edit: fn(&mut Scene)| {
            let mut scene = running.clone();
            edit(&mut scene);
            scene.change_from(&running)
        };
        assert_eq!(change(|_| {}), SceneChange::default());
        let outputs = SceneChange { outputs: true, ..Default::default() };
        assert_eq!(change(|s| s.camera.width = 640), outputs);
        assert_eq!(change(|s| s.stages.raycast = !s.stages.raycast), outputs);
        assert_eq!(change(|s| s.dpcm.rate_hz = 5.0), outputs);
        assert_eq!(change(|s| s.warp.rate_hz = 5.0), SceneChange { warp: true, ..outputs.clone() });
        assert_eq!(change(|s| s.inputs.max_age = 0.0), SceneChange { checks: true, ..Default::default() });
        assert!(change(|s| s.frame_id = "map".into()).checks);
        assert_eq!(change(|s| s.solver.dt = 0.005).physics, ["solver"]);
        assert_eq!(change(|s| s.stages.solver = false).physics, ["stages.solver"]);
        assert_eq!(change(|s| s.density = 900.0).physics, ["density"]);
        assert_eq!(change(|s| s.tools[0].contact_stiffness *= 2.0).physics, ["tools"]);
        assert_eq!(change(|s| s.volume = "ct.nii".into()).physics, ["volume"]);
    }

    #[test]
    fn default_scene_parses_and_rejects_unknown_fields() {
        let s = Scene::default_scene().unwrap();
        assert_eq!(s.tools.len(), 1);
        let bad = DEFAULT_SCENE.replace("density: 1000.0", "densty: 1000.0");
        let e = Scene::parse(&bad, "s.yaml").unwrap_err().to_string();
        assert!(e.contains("s.yaml") && e.contains("unknown field") && e.contains("did you mean `density`"), "{e}");
        // Inside a tagged section too, with the names it takes.
        let bad = DEFAULT_SCENE.replace("  stiffness: 1000.0", "  stifness: 1000.0");
        let e = Scene::parse(&bad, "s.yaml").unwrap_err().to_string();
        assert!(e.contains("material: unknown field") && e.contains("`stiffness`"), "{e}");
        assert!(e.ends_with("at line 9 (did you mean `stiffness`?)"), "the line of the section: {e}");
    }

    /// The cases: `dt: 10` ran 2 steps to t = 20 s, a radius typed in mm for m
    /// "diverged at step 1". Both are refused at once, by their paths and ranges, before
    /// the volume is read; a large but possible radius is warned of instead.
    #[test]
    fn scene_values_outside_their_parameters_ranges_are_refused_by_path() {
        let mut scene = Scene::default_scene().unwrap();
        scene.solver.dt = 10.0;
        scene.tools[0].shape = ToolShape::Sphere { radius: 2.0 };
        scene.volume = "no/such/ct.nii.gz".into();
        let e = scene.load().err().unwrap().to_string();
        assert!(e.contains("solver.dt = 10.0 is outside [1e-6, 0.1] (Solver time step (s)"), "{e}");
        assert!(e.contains("tools.0.shape.radius = 2.0 is outside [1e-5, 1] (Tool radius (m))"), "{e}");
        assert!(!e.contains("ct.nii.gz"), "refused before the volume is read: {e}");
        let mut nan = Scene::default_scene().unwrap();
        nan.file_to_world = f64::NAN;
        let e = nan.load().err().unwrap().to_string();
        assert!(e.contains("file_to_world = .nan is outside [1e-9, 1000]"), "{e}");
    }

    /// A scene names what it needs (the newcomer wrote a volume and a mesh): every
    /// other field is the embedded scene's, `mesh: FILE` is a mesh file, a section of another
    /// kind replaces the default's whole, a tool inherits the default's first tool.
    #[test]
    fn a_scene_names_what_it_needs_and_inherits_the_rest() {
        let default = Scene::default_scene().unwrap();
        let scene = Scene::parse("volume: ct.nii.gz\nmesh: organ.vtu\nsolver: {dt: 0.005}\n", "s.yaml").unwrap();
        assert_eq!(scene.mesh, MeshSource::File { path: "organ.vtu".into(), scale: None });
        assert_eq!((scene.volume.as_str(), scene.solver.dt), ("ct.nii.gz", 0.005));
        assert_eq!(
            Scene { volume: default.volume.clone(), mesh: default.mesh.clone(), ..scene.clone() }.solver.dt,
            0.005
        );
        assert_eq!(
            (&scene.material, &scene.tools, &scene.camera),
            (&default.material, &default.tools, &default.camera)
        );
        assert_eq!(scene.solver.cg_tolerance, default.solver.cg_tolerance);
        let needle = "tools: [{name: needle, shape: {kind: capsule, radius: 0.001, length: 0.05}, \
                      contact_stiffness: 5000, spread_radius: 0.01}]\n";
        let scene = Scene::parse(needle, "s.yaml").unwrap();
        assert_eq!(scene.tools[0].shape, ToolShape::Capsule { radius: 0.001, length: 0.05 });
        assert_eq!((scene.tools[0].name.as_str(), scene.tools[0].coupling), ("needle", None), "a tool as written");
        let lowest = Scene::parse("fixed: {kind: lowest}\n", "s.yaml").unwrap();
        assert_eq!(lowest.fixed, Some(FixedNodes::Lowest { fraction: FixedNodes::LOWEST_FRACTION }));
    }

    /// Relative paths in a scene file are the file's neighbours, not the working folder's.
    #[test]
    fn files_a_scene_names_lie_beside_it() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("scene.yaml");
        std::fs::write(&file, "volume: ct/ct.nii.gz\nmesh: {kind: file, path: organ.vtu, scale: 0.001}\n").unwrap();
        let scene = Scene::from_file(&file).unwrap();
        assert_eq!(Path::new(&scene.volume), dir.path().join("ct/ct.nii.gz"));
        assert_eq!(scene.mesh, MeshSource::File { path: dir.path().join("organ.vtu"), scale: Some(0.001) });
        std::fs::write(&file, "volume: /data/ct.nii.gz\n").unwrap();
        let scene = Scene::from_file(&file).unwrap();
        assert_eq!((scene.volume.as_str(), &scene.mesh), ("/data/ct.nii.gz", &Scene::default_scene().unwrap().mesh));
    }

    /// A section of the wrong shape is named with the kinds it takes, and its line.
    #[test]
    fn a_section_of_the_wrong_shape_lists_its_kinds() {
        let e = Scene::parse("volume: ct.nii.gz\nmesh: 5\n", "s.yaml").unwrap_err().to_string();
        assert!(e.contains("mesh: invalid type"), "{e}");
        assert!(e.contains("(kind: one of file, volume_lattice, lattice, bar, ellipsoid) at line 2"), "{e}");
        let e = Scene::parse("fixed: {kind: plank}\n", "s.yaml").unwrap_err().to_string();
        assert!(e.contains("fixed.kind: unknown variant, expected one of `indices`, `box`, `plane`, `lowest`"), "{e}");
        assert!(e.contains("at line 1 (did you mean `plane`?)"), "{e}");
    }

    #[test]
    fn tool_path_interpolates_then_holds() {
        let p = ToolPath { from: [0.0; 3], to: [1.0, 0.0, 0.0], duration: 2.0 };
        assert_eq!(p.position(1.0).x, 0.5);
        assert_eq!(p.position(5.0).x, 1.0);
    }
}
