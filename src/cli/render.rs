//! `defvol render`: a raycast image of a volume (the phantom when no file is given).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use nalgebra::{Point3, Vector3};

use defvol::backend::BackendChoice;
use defvol::render::camera::{Camera, Projection};
use defvol::render::engine::{MeshRenderer, Shown, VolumeRenderer};
use defvol::render::mesh::source::SourceSampling;
use defvol::render::mesh::{TetRaycastParams, TetRaycaster};
use defvol::render::transfer::TransferFunction;
use defvol::render::volume::{self, RaycastParams, VolumeRaycaster};
use defvol::scene::BackendArgs;
use defvol::volume::{phantom, Volume};

use super::choices::{CliMode, CliSampling, CliShading};

#[derive(clap::Args)]
pub struct RenderArgs {
    /// Volume file (.nii/.nii.gz/.nrrd/.nhdr/.mha/.mhd/.dcm) or a folder of DICOM slices;
    /// the phantom when absent.
    #[arg(long)]
    volume: Option<PathBuf>,
    /// With a DICOM folder: the series to read (its SeriesInstanceUID); default the largest.
    #[arg(long, requires = "volume")]
    series: Option<String>,
    /// Render a tetrahedral mesh instead (.vtu, .vtk, .msh, .node/.ele), in the volume's
    /// world units. Its node scalars are the file's, or sampled from --volume (or the
    /// phantom) at the nodes.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// With --mesh: the node values to render, a named one-component point array of the
    /// .vtu/.vtk file (instead of its scalars or values sampled from the volume).
    #[arg(long, requires = "mesh")]
    scalars: Option<String>,
    /// With --mesh as the rest mesh: the same mesh deformed (same nodes and tets). The
    /// picture is the source volume (--volume, or the phantom) seen through the deformed
    /// mesh, each sample mapped back to rest: the deformed scan with no warp. --step is then
    /// the sample spacing (default: the source's finest voxel spacing).
    #[arg(long, requires = "mesh", conflicts_with = "scalars")]
    deformed: Option<PathBuf>,
    /// With --deformed: how the source is read at each sample's rest position.
    #[arg(long, value_enum, default_value = "trilinear", requires = "deformed")]
    sampling: CliSampling,
    /// With --deformed: a displacement volume "cx,cy,cz:dx,dy,dz:extent" in the source's
    /// units, a backward distortion on top of the mesh's (repeatable; applied in order).
    #[arg(long, requires = "deformed")]
    displace: Vec<String>,
    /// Volume units per mesh unit (1000 for a metre mesh over a millimetre volume). Default:
    /// from the unit the mesh file records (defvol's files do), else 1.
    #[arg(long, value_parser = super::checks::mesh_scale)]
    mesh_scale: Option<f64>,
    /// Transfer-function preset: ct_soft_tissue, ct_bone, mri.
    #[arg(long, default_value = "ct_soft_tissue")]
    tf: String,
    /// A transfer function as YAML (`points: [{value, color: [r, g, b], opacity}]`,
    /// `relative: bool`), instead of the preset.
    #[arg(long)]
    tf_file: Option<PathBuf>,
    /// Image size, WxH.
    #[arg(long, default_value = "512x512")]
    size: String,
    /// Camera: `EYE:TARGET` as x,y,z:x,y,z in the volume's world units (mm for medical
    /// files); default: the bench view of the whole volume.
    #[arg(long)]
    camera: Option<String>,
    #[arg(long, value_delimiter = ',', num_args = 3, default_value = "0,0,1")]
    up: Vec<f64>,
    /// Vertical field of view, degrees.
    #[arg(long, default_value_t = 45.0)]
    fov: f64,
    /// Orthographic view of this height instead of perspective.
    #[arg(long)]
    ortho: Option<f64>,
    #[arg(long, value_enum, default_value = "composite")]
    mode: CliMode,
    /// Iso value for --mode iso.
    #[arg(long, default_value_t = 300.0)]
    iso: f64,
    #[arg(long, value_enum, default_value = "gradient")]
    shading: CliShading,
    /// Sample spacing along rays (world units; default 1). With --mesh and pre-integration:
    /// the longest piece of a tet's segment one table lookup covers (default 4).
    #[arg(long)]
    step: Option<f64>,
    /// Point sampling instead of pre-integrated segments.
    #[arg(long)]
    no_preintegration: bool,
    /// A tool in the picture: `TIP:TAIL:RADIUS` (x,y,z:x,y,z:r, world units; a sphere when
    /// tip and tail coincide). Repeat for more tools (up to 4).
    #[arg(long)]
    tool: Vec<String>,
    #[arg(long, default_value = "render.png")]
    out: PathBuf,
    #[command(flatten)]
    backend: BackendArgs,
    /// Also write the depth along each ray (world units; 0 where nothing was hit) as a
    /// float image (.mha, .nrrd, .nii).
    #[arg(long)]
    depth_out: Option<PathBuf>,
}

fn tool(text: &str) -> Result<volume::ToolPicture> {
    let parts: Vec<&str> = text.split(':').collect();
    let [tip, tail, radius] = parts[..] else { bail!("--tool `{text}`: expected TIP:TAIL:RADIUS as x,y,z:x,y,z:r") };
    let radius: f64 = radius.trim().parse().with_context(|| format!("--tool `{text}`: bad radius"))?;
    Ok(volume::ToolPicture {
        tip: point(tip)?.coords.into(),
        tail: point(tail)?.coords.into(),
        radius,
        color: [0.75, 0.78, 0.82],
    })
}

fn point(text: &str) -> Result<Point3<f64>> {
    let v: Vec<f64> = text
        .split(',')
        .map(|c| c.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("`{text}` is not x,y,z"))?;
    let [x, y, z] = v[..] else { bail!("`{text}` is not x,y,z") };
    Ok(Point3::new(x, y, z))
}

pub fn run(args: RenderArgs) -> Result<()> {
    // Outputs are checked before the work: a wrong name costs nothing.
    super::checks::check_png_output(&args.out)?;
    if let Some(path) = &args.depth_out {
        defvol::io::check_volume_output(path)?;
    }
    let volume: Volume = match &args.volume {
        Some(path) => defvol::io::read_volume_series(path, args.series.as_deref())?,
        None => phantom::phantom(phantom::DEFAULT_DIMS, 1.0)?,
    };
    let tf = match &args.tf_file {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
            serde_yaml_ng::from_str::<TransferFunction>(&text).map_err(|e| {
                anyhow::anyhow!(
                    "{}: not a transfer function: {}",
                    path.display(),
                    defvol::io::withhold_found(&e.to_string())
                )
            })?
        }
        None => TransferFunction::preset(&args.tf)?,
    };
    let Some((w, h)) = args
        .size
        .split_once('x')
        .and_then(|(w, h)| Some((w.trim().parse::<usize>().ok()?, h.trim().parse::<usize>().ok()?)))
    else {
        bail!("--size `{}`: expected WxH, e.g. 512x512", args.size)
    };
    let projection = match args.ortho {
        Some(height) => Projection::Orthographic { height },
        None => Projection::Perspective { fov_y_deg: args.fov },
    };
    let camera = match &args.camera {
        Some(text) => {
            let Some((eye, target)) = text.split_once(':') else {
                bail!("--camera `{text}`: expected EYE:TARGET as x,y,z:x,y,z")
            };
            let up = Vector3::new(args.up[0], args.up[1], args.up[2]);
            Camera::look_at(point(eye)?, point(target)?, up, projection, w, h)?
        }
        None => {
            let mut camera = defvol::bench::render::phantom_camera(&volume, w.max(h))?;
            (camera.width, camera.height, camera.projection) = (w, h, projection);
            camera.validate()?;
            camera
        }
    };
    let tools = args.tool.iter().map(|t| tool(t)).collect::<Result<Vec<_>>>()?;
    let params = RaycastParams {
        mode: args.mode.into(),
        step: args.step.unwrap_or(1.0),
        preintegrated: !args.no_preintegration,
        shading: args.shading.into(),
        iso_value: args.iso,
        tools: tools.clone(),
        ..Default::default()
    };
    let backend = args.backend.choose_or(BackendChoice::Auto)?;
    let started = std::time::Instant::now();
    let (image, on) = match &args.mesh {
        Some(path) => {
            let (mesh, scale) = super::checks::mesh_over_volume(path, args.mesh_scale)?;
            super::checks::check_mesh_meets_volume(&path.display().to_string(), mesh.nodes(), scale, &volume)?;
            if let Some(deformed_path) = &args.deformed {
                let deformed = super::checks::deformed_positions(deformed_path, &mesh, args.mesh_scale, scale)?;
                let sampling = SourceSampling {
                    sampling: args.sampling.into(),
                    displacements: args
                        .displace
                        .iter()
                        .map(|d| super::warp::parse_displacement(d))
                        .collect::<Result<Vec<_>>>()?,
                };
                let tets = mesh.tets().len();
                // Samples about a voxel apart: the step follows the source, not the mesh.
                let finest = volume.spacing().iter().copied().fold(f64::INFINITY, f64::min);
                let params = RaycastParams { step: args.step.unwrap_or(finest), ..params.clone() };
                let mut raycaster =
                    TetRaycaster::with_source(&mesh, std::sync::Arc::new(volume.clone()), &tf, &params, &sampling)?;
                raycaster.update(&deformed)?;
                let mut renderer = MeshRenderer::new(&backend, raycaster, 1.0)?;
                let image = renderer.render(&tools, &camera)?;
                let on =
                    format!("the source through {tets} deformed tets, {} ({})", renderer.runs_on(), backend.describe());
                return finish(&args, image, &on, started, (w, h));
            }
            let scalars: Vec<f32> = match (&args.scalars, mesh.scalars(), &args.volume) {
                (Some(name), _, _) => defvol::io::read_mesh_point_array(path, name)?,
                (None, Some(s), None) => s.to_vec(),
                _ => {
                    let outside = volume.range().0;
                    mesh.nodes().iter().map(|p| volume.sample_world(*p).unwrap_or(outside)).collect()
                }
            };
            let preintegrated = !args.no_preintegration;
            let step = args.step.unwrap_or(if preintegrated { 4.0 } else { 1.0 });
            let tet_params = TetRaycastParams {
                step,
                preintegrated,
                background: params.background,
                tools: params.tools.clone(),
                ambient: params.ambient,
                ..Default::default()
            };
            let raycaster = TetRaycaster::new(&mesh, &scalars, &tf, &tet_params)?;
            let mut renderer = MeshRenderer::new(&backend, raycaster, 1.0)?;
            let image = renderer.render(&tools, &camera)?;
            (image, format!("{} ({}), {} tets", renderer.runs_on(), backend.describe(), mesh.tets().len()))
        }
        None => {
            let tables = std::sync::Arc::new(VolumeRaycaster::tables_for(volume.range(), &tf, &params)?);
            let mut renderer = VolumeRenderer::new(&backend, &volume, tables, &params)?;
            let image = renderer.render(Shown::Host(&volume), &tools, &camera)?;
            (image, format!("{} ({})", renderer.runs_on(), backend.describe()))
        }
    };
    finish(&args, image, &on, started, (w, h))
}

/// Logs the frame and writes the picture (and the depth, when asked).
fn finish(
    args: &RenderArgs,
    image: defvol::render::Rendered,
    on: &str,
    started: std::time::Instant,
    (w, h): (usize, usize),
) -> Result<()> {
    tracing::info!("rendered {w}x{h} on {on} in {:.1} ms", started.elapsed().as_secs_f64() * 1e3);
    if image.rgba.chunks_exact(4).all(|pixel| pixel == &image.rgba[..4]) {
        tracing::warn!(
            "the picture is one colour: nothing is in view (the camera, the transfer function's opacity, or the \
             mesh's unit?)"
        );
    }
    image.write_png(&args.out)?;
    tracing::info!("wrote {}", args.out.display());
    if let Some(path) = &args.depth_out {
        let depth: Vec<f32> = image.depth.iter().map(|d| if d.is_finite() { *d } else { 0.0 }).collect();
        let out = Volume::new(
            [w, h, 1],
            [1.0; 3],
            [0.0; 3],
            nalgebra::Matrix3::identity(),
            depth,
            &path.display().to_string(),
        )?;
        defvol::io::write_volume(path, &out)?;
        tracing::info!("wrote {}", path.display());
    }
    Ok(())
}
