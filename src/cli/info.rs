//! `defvol info PATH`: what a user needs to see of a file before simulating it. A volume:
//! dims, spacing, origin, direction, value range and units, and for DICOM its series; a
//! mesh: node and tet counts, bounds and quality (dihedral angles, inverted tets).

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
        mesh_info(&io::read_mesh_with_metadata(&args.path)?)
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

fn mesh_info(read: &io::MeshRead) -> Value {
    let mesh = &read.mesh;
    let (lo, hi) = mesh.bounds();
    // A cell array's distinct values (Gmsh's regions: a handful each).
    let regions = |values: &[f32]| {
        let mut distinct: Vec<f32> = values.to_vec();
        distinct.sort_by(f32::total_cmp);
        distinct.dedup();
        distinct
    };
    let cell_arrays: serde_json::Map<String, Value> =
        read.cell_arrays.iter().map(|a| (a.name.clone(), json!(regions(&a.values)))).collect();
    let (min, max) = mesh.dihedral_range();
    json!({
        "kind": "mesh",
        "nodes": mesh.nodes().len(),
        "tets": mesh.tets().len(),
        "bounds": [[lo.x, lo.y, lo.z], [hi.x, hi.y, hi.z]],
        "min_dihedral_deg": min.to_degrees(),
        "max_dihedral_deg": max.to_degrees(),
        // A mesh with some tets inverted is refused when read (naming one); all inverted
        // is the other handedness, flipped whole.
        "inverted_tets": 0,
        "unused_nodes_dropped": read.unused_nodes,
        "cells_split_into_tets": read.split,
        "other_cells_skipped": read.skipped,
        "cell_arrays": cell_arrays,
    })
}

/// The JSON's fields as `key: value` lines.
fn print_text(path: &str, info: &Value) {
    println!("{path}");
    for (key, value) in info.as_object().into_iter().flatten() {
        println!("  {key}: {value}");
    }
}
