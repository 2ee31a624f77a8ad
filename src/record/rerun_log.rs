//! Session logs for the rerun viewer: the deformed surface as a Mesh3D, the tools with
//! their transforms and shapes, the raycast camera as a pinhole with its image in 3-D, the
//! warped volume's box and its three orthogonal slices through the tool, the DPCM images,
//! and the diagnostics as plots, on a `sim_time` timeline.

use std::path::Path;

use nalgebra::Vector3;

use crate::msgs::{DeformedMesh, DiagnosticArray, Image, WarpedVolumeInfo, WrenchStamped};
use crate::scene::{CameraConfig, ToolConfig};
use crate::solver::ToolShape;
use crate::volume::Grid;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RerunError {
    #[error("rerun: {0}")]
    Stream(String),
    #[error("rerun: {0}")]
    Log(String),
}

pub struct RerunLog {
    stream: rerun::RecordingStream,
}

impl RerunLog {
    /// A log written to an `.rrd` file.
    pub fn save(path: &Path) -> Result<Self, RerunError> {
        let stream = rerun::RecordingStreamBuilder::new("defvol")
            .save(path)
            .map_err(|e| RerunError::Stream(format!("{}: {e}", path.display())))?;
        Ok(Self { stream })
    }

    /// A log streamed to a running viewer (`rerun+http://127.0.0.1:9876/proxy`).
    pub fn connect(url: &str) -> Result<Self, RerunError> {
        let stream = rerun::RecordingStreamBuilder::new("defvol")
            .connect_grpc_opts(url.to_owned())
            .map_err(|e| RerunError::Stream(format!("{url}: {e}")))?;
        Ok(Self { stream })
    }

    fn log(&self, path: &str, what: &impl rerun::AsComponents) -> Result<(), RerunError> {
        self.stream.log(path, what).map_err(|e| RerunError::Log(format!("{path}: {e}")))
    }

    /// One benchmark series as static 2D points (x: log10 ms, y: log10 error or dB), in the
    /// colour of its SVG curve, labelled.
    pub fn log_bench_series(
        &self,
        path: &str,
        points: &[[f32; 2]],
        rgb: [u8; 3],
        label: &str,
    ) -> Result<(), RerunError> {
        let points = rerun::Points2D::new(points.iter().copied())
            .with_colors([rerun::Color::from_rgb(rgb[0], rgb[1], rgb[2])])
            .with_labels([label]);
        self.stream.log_static(path, &points).map_err(|e| RerunError::Log(format!("{path}: {e}")))
    }

    /// A markdown note, static (what a view's axes mean).
    pub fn log_markdown(&self, path: &str, markdown: &str) -> Result<(), RerunError> {
        let text = rerun::TextDocument::from_markdown(markdown);
        self.stream.log_static(path, &text).map_err(|e| RerunError::Log(format!("{path}: {e}")))
    }

    /// The tools' shapes, once (they move through their transforms).
    pub fn log_tool_shapes(&self, tools: &[ToolConfig]) -> Result<(), RerunError> {
        for tool in tools {
            let path = format!("world/tools/{}", tool.name);
            let logged = match tool.shape {
                ToolShape::Sphere { radius } => self.stream.log_static(
                    path.as_str(),
                    &rerun::Ellipsoids3D::from_radii([radius as f32])
                        .with_colors([rerun::Color::from_rgb(190, 200, 210)]),
                ),
                ToolShape::Capsule { radius, length } => self.stream.log_static(
                    path.as_str(),
                    &rerun::Capsules3D::from_lengths_and_radii([length as f32], [radius as f32])
                        .with_colors([rerun::Color::from_rgb(190, 200, 210)]),
                ),
            };
            logged.map_err(|e| RerunError::Log(format!("{path}: {e}")))?;
        }
        Ok(())
    }

    pub fn set_time(&self, sim_time: f64) {
        self.stream.set_duration_secs("sim_time", sim_time);
    }

    pub fn log_tool_pose(&self, name: &str, world_from_tool: &nalgebra::Isometry3<f64>) -> Result<(), RerunError> {
        let (t, q) =
            (world_from_tool.translation.vector.cast::<f32>(), world_from_tool.rotation.quaternion().cast::<f32>());
        self.log(
            &format!("world/tools/{name}"),
            &rerun::Transform3D::from_translation_rotation(
                [t.x, t.y, t.z],
                rerun::Quaternion::from_xyzw([q.i, q.j, q.k, q.w]),
            ),
        )
    }

    /// The boundary surface coloured by displacement, and the peak displacement as a plot.
    pub fn log_mesh(&self, mesh: &DeformedMesh) -> Result<(), RerunError> {
        let positions: Vec<[f32; 3]> = mesh.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
        let triangles: Vec<[u32; 3]> = mesh.triangles.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
        let peak = mesh.scalars.iter().fold(1e-9f32, |m, d| m.max(*d));
        let colors: Vec<rerun::Color> = mesh
            .scalars
            .iter()
            .map(|d| {
                let c = colorous::VIRIDIS.eval_continuous(f64::from(d / peak));
                rerun::Color::from_rgb(c.r, c.g, c.b)
            })
            .collect();
        self.log(
            "world/organ",
            &rerun::Mesh3D::new(positions).with_triangle_indices(triangles).with_vertex_colors(colors),
        )?;
        self.log("plots/max_displacement_m", &rerun::Scalars::single(f64::from(peak)))
    }

    /// The reaction on the tool named `tool`.
    pub fn log_feedback(&self, tool: &str, feedback: &WrenchStamped) -> Result<(), RerunError> {
        let f = feedback.wrench.force;
        self.log(&format!("plots/tool_force_n/{tool}"), &rerun::Scalars::new([f.x, f.y, f.z]))
    }

    /// Where the warped volume lies: its voxel box (centres, in index units) under a
    /// transform from index to world, origin + direction · diag(spacing), scaled from the
    /// volume's units to the world's, so a viewer places it as ITK does.
    pub fn log_warped_volume(&self, info: &WarpedVolumeInfo, file_to_world: f64) -> Result<(), RerunError> {
        let d = info.direction;
        let column = |c: usize| [0, 1, 2].map(|r| (d[3 * r + c] * info.spacing[c] * file_to_world) as f32);
        let origin = info.origin.map(|o| (o * file_to_world) as f32);
        let transform = rerun::Transform3D::from_translation_mat3x3(origin, [column(0), column(1), column(2)]);
        self.log("world/warped_volume", &transform)?;
        let half = info.dims.map(|n| n.saturating_sub(1) as f32 / 2.0);
        self.log(
            "world/warped_volume",
            &rerun::Boxes3D::from_centers_and_half_sizes([half], [half])
                .with_colors([rerun::Color::from_rgb(120, 160, 220)]),
        )
    }

    /// The raycast camera where it looks from (world metres), as a pinhole whose image
    /// (`world/camera/image`) the 3-D view draws in its frustum.
    pub fn log_camera(&self, camera: &CameraConfig) -> Result<(), RerunError> {
        let (eye, target, up) = (Vector3::from(camera.eye), Vector3::from(camera.target), Vector3::from(camera.up));
        let forward = (target - eye).normalize();
        let right = forward.cross(&up).normalize();
        // rerun's pinhole looks along +z with x right and y down (RDF).
        let down = forward.cross(&right);
        let column = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
        let transform =
            rerun::Transform3D::from_translation_mat3x3(column(eye), [column(right), column(down), column(forward)]);
        self.log("world/camera", &transform)?;
        let (width, height) = (camera.width as f32, camera.height as f32);
        let focal = height / 2.0 / (camera.fov_y_deg.to_radians() as f32 / 2.0).tan();
        self.log("world/camera", &rerun::Pinhole::from_focal_length_and_resolution([focal, focal], [width, height]))
    }

    /// Three orthogonal slices of the warped volume (`samples` on `grid`, file units) through
    /// the point `at` (file units): axial, coronal and sagittal, as a medical viewer's slice
    /// views show them (superior up).
    pub fn log_slices(&self, samples: &[f32], grid: &Grid, at: Vector3<f64>) -> Result<(), RerunError> {
        for (view, data, [width, height]) in slices(samples, grid, at)? {
            let image = rerun::Image::from_elements(&data, [width as u32, height as u32], rerun::ColorModel::L);
            self.log(&format!("slices/{view}"), &image)?;
        }
        Ok(())
    }

    /// An RGB8/RGBA8 image, or a 32FC1 one as a depth image (metres).
    pub fn log_image(&self, path: &str, image: &Image) -> Result<(), RerunError> {
        let size = [image.width, image.height];
        match image.encoding.as_str() {
            "rgba8" => self.log(path, &rerun::Image::from_rgba32(image.data.clone(), size)),
            "rgb8" => self.log(path, &rerun::Image::from_rgb24(image.data.clone(), size)),
            "32FC1" => self.log(
                path,
                &rerun::DepthImage::from_data_type_and_bytes(image.data.clone(), size, rerun::ChannelDatatype::F32)
                    .with_meter(1.0),
            ),
            other => Err(RerunError::Log(format!("{path}: no rerun form for encoding {other}"))),
        }
    }

    /// Every numeric diagnostic value as a plot under `diagnostics/<status>/<key>`.
    pub fn log_diagnostics(&self, diagnostics: &DiagnosticArray) -> Result<(), RerunError> {
        for status in &diagnostics.status {
            let group = status.name.trim_start_matches("defvol: ");
            for kv in &status.values {
                if let Ok(value) = kv.value.parse::<f64>() {
                    self.log(&format!("diagnostics/{group}/{}", kv.key), &rerun::Scalars::single(value))?;
                }
            }
        }
        Ok(())
    }

    pub fn flush(&self) -> Result<(), RerunError> {
        self.stream.flush_blocking().map_err(|e| RerunError::Stream(e.to_string()))
    }
}

/// One slice: its view's name, its samples row by row, its width and height.
type Slice = (&'static str, Vec<f32>, [usize; 2]);

/// The axial (rows along y), coronal and sagittal (rows from the top slice down) planes of
/// `samples` on `grid` through the voxel nearest `at` (file units), each with its size.
fn slices(samples: &[f32], grid: &Grid, at: Vector3<f64>) -> Result<[Slice; 3], RerunError> {
    let [nx, ny, nz] = grid.dims;
    if samples.len() != nx * ny * nz || samples.is_empty() {
        return Err(RerunError::Log(format!("warped volume: {} samples for {nx}x{ny}x{nz}", samples.len())));
    }
    let index = grid.index_from_world(at);
    let clamp = |v: f64, n: usize| (v.round().max(0.0) as usize).min(n - 1);
    let (i, j, k) = (clamp(index.x, nx), clamp(index.y, ny), clamp(index.z, nz));
    let at = |x: usize, y: usize, z: usize| samples[x + nx * (y + ny * z)];
    let axial = (0..ny).flat_map(|y| (0..nx).map(move |x| at(x, y, k))).collect();
    let coronal = (0..nz).rev().flat_map(|z| (0..nx).map(move |x| at(x, j, z))).collect();
    let sagittal = (0..nz).rev().flat_map(|z| (0..ny).map(move |y| at(i, y, z))).collect();
    Ok([("axial", axial, [nx, ny]), ("coronal", coronal, [nx, nz]), ("sagittal", sagittal, [ny, nz])])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a volume whose sample encodes its own index, each plane holds exactly the voxels
    /// through the point's nearest voxel, found through the grid's spacing and origin.
    #[test]
    fn the_three_slices_cross_at_the_voxel_nearest_the_point() {
        let grid = Grid {
            dims: [4, 3, 5],
            spacing: [2.0, 1.0, 0.5],
            origin: [10.0, 0.0, -1.0],
            direction: nalgebra::Matrix3::identity(),
        };
        let code = |x: usize, y: usize, z: usize| (x * 100 + y * 10 + z) as f32;
        let samples: Vec<f32> =
            (0..5).flat_map(|z| (0..3).flat_map(move |y| (0..4).map(move |x| code(x, y, z)))).collect();
        // (14.2, 1.1, 0.4) is voxel (2.1, 1.1, 2.8) -> (2, 1, 3).
        let [axial, coronal, sagittal] = slices(&samples, &grid, Vector3::new(14.2, 1.1, 0.4)).unwrap();
        assert_eq!((axial.2, coronal.2, sagittal.2), ([4, 3], [4, 5], [3, 5]));
        assert!(axial.1.iter().all(|v| *v as usize % 10 == 3) && axial.1[4 + 1] == code(1, 1, 3));
        assert!(coronal.1.iter().all(|v| (*v as usize / 10) % 10 == 1));
        assert_eq!((coronal.1[0], coronal.1[4 * 4 + 3]), (code(0, 1, 4), code(3, 1, 0)), "superior up");
        assert!(sagittal.1.iter().all(|v| *v as usize / 100 == 2) && sagittal.1[2] == code(2, 2, 4));
        assert!(slices(&samples[1..], &grid, Vector3::zeros()).is_err());
    }
}
