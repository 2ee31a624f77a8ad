//! `defvol info PATH`: what a user needs to see of a file before simulating it. A volume:
//! dims, spacing, origin, direction, value range and units, and for DICOM its series; a
//! mesh: counts, element quality and boundary topology, never refused once it parses.

use std::path::PathBuf;

use anyhow::Result;
use defvol::io;
use defvol::volume::Volume;
use serde_json::{json, Value};

#[derive(clap::Args)]
pub struct InfoArgs {
    /// A volume (.nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, .dcm, a DICOM folder) or a mesh
    /// (.vtu, .vtk, .msh, .node/.ele).
    path: PathBuf,
    /// With a DICOM folder: the series to describe (its SeriesInstanceUID).
    #[arg(long)]
    series: Option<String>,
    /// One JSON object instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(args: InfoArgs) -> Result<()> {
    let info = if io::is_mesh(&args.path) {
        mesh_info(&io::read_raw_mesh(&args.path)?)
    } else if io::is_dicom(&args.path) {
        let read = io::read_dicom(&args.path, args.series.as_deref())?;
        let mut info = volume_info(&read.volume, read.units.as_deref());
        info["series"] = series_info(&read.series);
        info["other_series"] = read.others.iter().map(series_info).collect();
        info["skipped_files"] = read.skipped.len().into();
        info
    } else {
        volume_info(&io::read_volume_series(&args.path, args.series.as_deref())?, None)
    };
    if args.json {
        println!("{info}");
    } else {
        print_text(&args.path.display().to_string(), &info);
    }
    Ok(())
}

fn series_info(s: &io::SeriesInfo) -> Value {
    json!({"uid": s.uid, "description": s.description, "files": s.files, "slices": s.slices})
}

fn volume_info(v: &Volume, units: Option<&str>) -> Value {
    let (low, high) = v.range();
    let d = v.direction();
    json!({
        "kind": "volume",
        "dims": v.dims(),
        "spacing": v.spacing(),
        "origin": v.origin(),
        "direction": [d[(0, 0)], d[(0, 1)], d[(0, 2)], d[(1, 0)], d[(1, 1)], d[(1, 2)], d[(2, 0)], d[(2, 1)], d[(2, 2)]],
        "range": [low, high],
        "units": units,
    })
}

/// A mesh as read, described whatever it holds: what the solver would refuse (inverted,
/// flat or broken tets, overlapping faces) is counted, not refused.
fn mesh_info(raw: &io::RawMesh) -> Value {
    let quality = defvol::mesh::quality(&raw.nodes, &raw.tets);
    // A cell array's distinct values (Gmsh's regions: a handful each).
    let regions = |values: &[f32]| {
        let mut distinct: Vec<f32> = values.to_vec();
        distinct.sort_by(f32::total_cmp);
        distinct.dedup();
        distinct
    };
    let cell_arrays: serde_json::Map<String, Value> =
        raw.cell_arrays.iter().map(|a| (a.name.clone(), json!(regions(&a.values)))).collect();
    let mut info = json!({"kind": "mesh"});
    if let (Value::Object(fields), Ok(Value::Object(measured))) = (&mut info, serde_json::to_value(&quality)) {
        fields.extend(measured);
    }
    info["slivers_under_deg"] = defvol::mesh::SLIVER_DEG.into();
    info["unused_nodes_dropped"] = raw.unused_nodes.into();
    info["metres_per_unit"] = json!(raw.metres_per_unit);
    info["cells_split_into_tets"] = json!(raw.split);
    info["other_cells_skipped"] = json!(raw.skipped);
    info["cell_arrays"] = Value::Object(cell_arrays);
    info
}

/// The JSON's fields as `key: value` lines.
fn print_text(path: &str, info: &Value) {
    println!("{path}");
    for (key, value) in info.as_object().into_iter().flatten() {
        println!("  {key}: {value}");
    }
}
