//! Session logs for the rerun viewer: the deformed surface as a Mesh3D, the tools with
//! their transforms and shapes, the raycast and DPCM images, and the diagnostics as plots,
//! on a `sim_time` timeline.

use std::path::Path;

use crate::msgs::{DeformedMesh, DiagnosticArray, Image, WarpedVolumeInfo, WrenchStamped};
use crate::scene::ToolConfig;
use crate::solver::ToolShape;

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
