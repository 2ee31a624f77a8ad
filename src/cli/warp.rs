//! `defvol warp`: a volume through a deformed mesh and/or displacement volumes; with no
//! files, the phantom through a generated bend.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use defvol::backend::Backend;
use defvol::backend::BackendChoice;
use defvol::io;
use defvol::mesh::TetMesh;
use defvol::scene::BackendArgs;
use defvol::volume::{Grid, Volume};
use defvol::warp::{DisplacementVolume, WarpOptions};

use super::choices::{CliSampling, CliScheme};

#[derive(clap::Args)]
pub struct WarpArgs {
    /// Rest mesh (.vtu, .vtk, .msh, .node/.ele), in the volume's physical units.
    #[arg(long, requires = "deformed")]
    rest: Option<PathBuf>,
    /// Deformed mesh: same topology, moved nodes.
    #[arg(long, requires = "rest")]
    deformed: Option<PathBuf>,
    /// Volume units per mesh unit (1000 for a metre mesh over a millimetre volume). Default:
    /// from the unit the mesh file records (defvol's files do), else 1.
    #[arg(long, value_parser = super::checks::mesh_scale)]
    mesh_scale: Option<f64>,
    /// Source volume (.nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, .dcm, or a folder of DICOM
    /// slices); the phantom when absent.
    #[arg(long)]
    volume: Option<PathBuf>,
    /// With a DICOM folder: the series to read (its SeriesInstanceUID); default the largest.
    #[arg(long, requires = "volume")]
    series: Option<String>,
    /// Output volume (.nii, .nii.gz, .nrrd, .mha, .mhd), in the source's units and conventions.
    #[arg(long)]
    out: PathBuf,
    /// A displacement volume "cx,cy,cz:dx,dy,dz:extent" (repeatable; applied in order).
    #[arg(long)]
    displace: Vec<String>,
    #[arg(long, value_enum, default_value = "spans")]
    scheme: CliScheme,
    #[arg(long, value_enum, default_value = "trilinear")]
    sampling: CliSampling,
    /// The value of voxels no tet covers. Default: the source's minimum, as the node uses
    /// (air for a CT in Hounsfield units, not 0, which is soft tissue there).
    #[arg(long, allow_negative_numbers = true)]
    background: Option<f32>,
    /// Voxels outside the mesh keep the source's value.
    #[arg(long)]
    keep_uncovered: bool,
    /// `auto` runs on the GPU only where the options allow (trilinear, no displacement
    /// volumes).
    #[command(flatten)]
    backend: BackendArgs,
}

pub(super) fn parse_displacement(text: &str) -> Result<DisplacementVolume> {
    let parts: Vec<&str> = text.split(':').collect();
    let vec3 = |s: &str| -> Result<[f64; 3]> {
        let v: Vec<f64> = s
            .split(',')
            .map(|c| c.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("`{s}` is not three numbers"))?;
        let [x, y, z] = v[..] else { bail!("`{s}` is not three numbers") };
        Ok([x, y, z])
    };
    let [centre, displacement, extent] = parts[..] else {
        bail!("--displace `{text}`: expected cx,cy,cz:dx,dy,dz:extent")
    };
    Ok(DisplacementVolume {
        centre: vec3(centre)?,
        displacement: vec3(displacement)?,
        extent: extent.trim().parse().with_context(|| format!("--displace `{text}`: bad extent"))?,
    })
}

pub fn run(args: WarpArgs) -> Result<()> {
    io::check_volume_output(&args.out)?;
    let source = match &args.volume {
        Some(path) => io::read_volume_series(path, args.series.as_deref())?,
        None => defvol::volume::phantom::phantom(defvol::volume::phantom::DEFAULT_DIMS, 1.0)?,
    };
    let displacements = args.displace.iter().map(|d| parse_displacement(d)).collect::<Result<Vec<_>>>()?;
    let options = WarpOptions {
        scheme: args.scheme.into(),
        sampling: args.sampling.into(),
        background: args.background.unwrap_or(source.range().0),
        keep_uncovered: args.keep_uncovered,
        displacements,
        ..Default::default()
    };
    let started = std::time::Instant::now();
    let result = match (&args.rest, &args.deformed) {
        (Some(rest_path), Some(deformed_path)) => {
            let (rest, scale) = super::checks::mesh_over_volume(rest_path, args.mesh_scale)?;
            let (deformed, _) = super::checks::mesh_over_volume(deformed_path, args.mesh_scale)?;
            super::checks::check_mesh_meets_volume(&rest_path.display().to_string(), rest.nodes(), scale, &source)?;
            if deformed.tets() != rest.tets() {
                bail!(
                    "{}: the deformed mesh's tets differ from the rest mesh's ({} vs {} tets, or other node order)",
                    deformed_path.display(),
                    deformed.tets().len(),
                    rest.tets().len()
                );
            }
            let grid = defvol::warp::default_grid(&source, deformed.nodes());
            warp_on_backend(&args, &source, &rest, deformed.nodes(), grid, &options)?
        }
        // Displacement volumes alone: no mesh, so no generated bend either.
        _ if !options.displacements.is_empty() => defvol::warp::displace(&source, &source.grid(), &options)?,
        _ => {
            // The phantom through a generated deformation: a bend.
            let (lo, hi) = source.bounds();
            let rest = defvol::mesh::generate::lattice_for_box(lo, hi, 700, defvol::mesh::generate::CellSplit::Five)?;
            let (centre, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
            let bent = defvol::bench::WarpCase::Bend.deform(rest.nodes(), centre, half);
            let grid = defvol::warp::default_grid(&source, &bent);
            warp_on_backend(&args, &source, &rest, &bent, grid, &options)?
        }
    };
    tracing::info!(
        "warped to {} voxels in {:.1} ms",
        defvol::logging::dims(result.dims()),
        started.elapsed().as_secs_f64() * 1e3
    );
    let (low, high) = result.range();
    if result.dims().iter().any(|d| *d < 2) || low == high {
        tracing::warn!(
            "the warped volume is degenerate ({} voxels, values {low} to {high}): does the mesh cover the source?",
            defvol::logging::dims(result.dims())
        );
    }
    io::write_volume(&args.out, &result)?;
    tracing::info!("wrote {}", args.out.display());
    Ok(())
}

fn describe(s: &defvol::warp::WarpStats) -> String {
    format!(
        "{} voxels, {} inside the mesh, {} candidates tested, {} inverted or degenerate tets skipped",
        s.voxels, s.inside, s.candidates, s.skipped_tets
    )
}

/// The warp on the chosen backend (`auto` falls back to the CPU for options only it has).
fn warp_on_backend(
    args: &WarpArgs,
    source: &Volume,
    rest: &TetMesh,
    deformed: &[nalgebra::Vector3<f64>],
    grid: Grid,
    options: &WarpOptions,
) -> Result<Volume> {
    let backend: Backend = args.backend.choose_or(BackendChoice::Auto)?;
    #[cfg(feature = "gpu")]
    if let Some(gpu) = backend
        .try_gpu("warp", |ctx| defvol::warp::gpu::GpuWarp::new(ctx.clone(), source, rest, grid.clone(), options, 1.0))?
    {
        let (data, stats) = gpu.warp(rest, deformed)?;
        tracing::info!("warped on the GPU: {}", describe(&stats));
        return Ok(Volume::from_grid(&grid, data, "warped volume")?);
    }
    #[cfg(not(feature = "gpu"))]
    let _ = backend;
    let (out, stats) = defvol::warp::warp(source, rest, deformed, &grid, options)?;
    tracing::info!("warped on the CPU: {}", describe(&stats));
    Ok(out)
}
