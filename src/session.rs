//! A run of the pipeline with its records: the topic names every driver (node, demo,
//! replay) uses, and the writing of inputs and outputs to MCAP and rerun. A recording that
//! fails stops with one error in the log and in `diagnostics`; the run goes on.

use std::path::PathBuf;

use crate::msgs::{Message, PoseStamped, Time, WrenchStamped};
use crate::pipeline::{Outputs, Pipeline};
use crate::record::Qos;

/// Output topics, relative to the node's namespace.
pub mod topics {
    pub const DEFORMED_MESH: &str = "deformed_mesh";
    pub const SURFACE_MARKER: &str = "surface_marker";
    pub const RAYCAST_IMAGE: &str = "raycast/image";
    pub const DPCM_HEIGHT: &str = "dpcm/height";
    pub const DPCM_IMAGE: &str = "dpcm/image";
    pub const WARPED_VOLUME_INFO: &str = "warped_volume/info";
    pub const DIAGNOSTICS: &str = "diagnostics";
}

/// `topic` under `namespace` ("/" or "/robot"), as ROS names it.
pub fn qualified(namespace: &str, topic: &str) -> String {
    if topic.starts_with('/') {
        return topic.to_owned();
    }
    format!("{}/{topic}", namespace.trim_end_matches('/'))
}

/// How a node names its topics: relative names under its namespace, ROS remaps applied
/// (`-r deformed_mesh:=mesh_out`). DDS, the recording and the log all name a topic so.
#[derive(Debug, Clone, Default)]
pub struct TopicNames {
    pub namespace: String,
    pub remaps: std::collections::BTreeMap<String, String>,
}

impl TopicNames {
    /// Names under `namespace` with no remaps (demo, replay, benches).
    pub fn under(namespace: &str) -> Self {
        Self { namespace: namespace.to_owned(), remaps: Default::default() }
    }

    /// The fully qualified name of `topic`, its remap (given relative or qualified) applied.
    pub fn resolve(&self, topic: &str) -> String {
        let full = qualified(&self.namespace, topic);
        let remapped = self.remaps.get(topic).or_else(|| self.remaps.get(&full));
        remapped.map_or(full, |to| qualified(&self.namespace, to))
    }
}

/// Where a session's records go.
#[derive(Debug, Clone, Default)]
pub struct RecordOptions {
    pub mcap: Option<PathBuf>,
    pub rerun_file: Option<PathBuf>,
    pub rerun_connect: Option<String>,
    /// How the MCAP recording splits (when `mcap` is a bag directory) and flushes.
    pub bag: crate::record::BagOptions,
}

impl RecordOptions {
    /// The first of the `n`th, `n + 1`th, … recordings whose files do not exist yet, and
    /// its number: a restarted node, or a managed one configured again, never records over
    /// what is there.
    pub fn unused_from(&self, n: u32) -> (Self, u32) {
        let taken = |o: &Self| o.mcap.iter().chain(&o.rerun_file).any(|p| p.exists());
        let mut n = n;
        while taken(&self.numbered(n)) && n < u32::MAX {
            n += 1;
        }
        (self.numbered(n), n)
    }

    /// The files of the `n`th recording of one run (`n` > 0: `session_n.mcap`, …).
    pub fn numbered(&self, n: u32) -> Self {
        let number = |path: &PathBuf| {
            if n == 0 {
                return path.clone();
            }
            let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let name = match path.extension() {
                Some(ext) => format!("{stem}_{n}.{}", ext.to_string_lossy()),
                None => format!("{stem}_{n}"),
            };
            path.with_file_name(name)
        };
        Self {
            mcap: self.mcap.as_ref().map(number),
            rerun_file: self.rerun_file.as_ref().map(number),
            rerun_connect: self.rerun_connect.clone(),
            bag: self.bag,
        }
    }
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SessionError {
    #[cfg(feature = "mcap")]
    #[error(transparent)]
    Record(#[from] crate::record::bag::RecordError),
    #[cfg(feature = "rerun")]
    #[error(transparent)]
    Rerun(#[from] crate::record::rerun_log::RerunError),
    #[error("{0} needs defvol built with the `{1}` feature")]
    NotBuilt(&'static str, &'static str),
}

/// The records of one run.
pub struct Session {
    #[cfg_attr(not(feature = "mcap"), allow(dead_code))]
    names: TopicNames,
    #[cfg(feature = "mcap")]
    bag: Option<crate::record::bag_thread::BagThread>,
    #[cfg(feature = "rerun")]
    rerun: Option<crate::record::rerun_log::RerunLog>,
    /// The first recording error, for diagnostics.
    pub record_error: Option<String>,
}

impl Session {
    pub fn open(names: &TopicNames, options: &RecordOptions, pipeline: &Pipeline) -> Result<Self, SessionError> {
        #[cfg(not(feature = "mcap"))]
        if options.mcap.is_some() {
            return Err(SessionError::NotBuilt("--record", "mcap"));
        }
        #[cfg(not(feature = "rerun"))]
        if options.rerun_file.is_some() || options.rerun_connect.is_some() {
            return Err(SessionError::NotBuilt("--rerun", "rerun"));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = pipeline;
        Ok(Self {
            names: names.clone(),
            #[cfg(feature = "mcap")]
            bag: options
                .mcap
                .as_deref()
                .map(|path| crate::record::bag_thread::BagThread::create(path, options.bag))
                .transpose()?,
            #[cfg(feature = "rerun")]
            rerun: {
                let log = match (&options.rerun_file, &options.rerun_connect) {
                    (Some(path), _) => Some(crate::record::rerun_log::RerunLog::save(path)?),
                    (None, Some(url)) => Some(crate::record::rerun_log::RerunLog::connect(url)?),
                    (None, None) => None,
                };
                if let Some(log) = &log {
                    log.log_tool_shapes(&pipeline.scene().tools)?;
                }
                log
            },
            record_error: None,
        })
    }

    /// Whether anything is recorded (then every output is wanted).
    pub fn recording(&self) -> bool {
        #[cfg(feature = "mcap")]
        if self.bag.is_some() {
            return true;
        }
        #[cfg(feature = "rerun")]
        if self.rerun.is_some() {
            return true;
        }
        false
    }

    #[cfg_attr(not(feature = "mcap"), allow(dead_code))]
    fn note_error(&mut self, what: &str, error: impl std::fmt::Display) {
        if self.record_error.is_none() {
            tracing::error!("{what} stopped: {error}; the run goes on without it");
            self.record_error = Some(format!("{what}: {error}"));
        }
    }

    #[cfg_attr(not(feature = "mcap"), allow(unused_variables))]
    fn bag_write<T: Message>(&mut self, topic: &str, qos: Qos, msg: &T, stamp: Time) {
        #[cfg(feature = "mcap")]
        if let Some(bag) = &self.bag {
            // After a failure every write says so; the log and diagnostics take the first.
            if let Err(e) = bag.write(&self.names.resolve(topic), qos, msg, stamp.as_nanos()) {
                self.note_error("MCAP recording", e);
            }
        }
    }

    /// Records a tool pose as received; `tool` (its name and accepted pose) moves the tool in
    /// the rerun log.
    pub fn record_pose(&mut self, topic: &str, msg: &PoseStamped, tool: Option<(&str, nalgebra::Isometry3<f64>)>) {
        self.bag_write(topic, Qos::SensorData, msg, msg.header.stamp);
        #[cfg(feature = "rerun")]
        if let (Some(log), Some((name, pose))) = (&self.rerun, tool) {
            log.set_time(msg.header.stamp.as_secs());
            if let Err(e) = log.log_tool_pose(name, &pose) {
                self.note_error("rerun log", e);
            }
        }
        #[cfg(not(feature = "rerun"))]
        let _ = tool;
    }

    pub fn record_wrench(&mut self, topic: &str, msg: &WrenchStamped) {
        self.bag_write(topic, Qos::SensorData, msg, msg.header.stamp);
    }

    /// Records one tool's feedback, published at `stamp` apart from a tick's outputs.
    pub fn record_feedback(&mut self, topic: &str, msg: &WrenchStamped, stamp: Time) {
        self.bag_write(topic, Qos::SensorData, msg, stamp);
    }

    /// Records every output of a tick.
    pub fn record_outputs(&mut self, out: &Outputs, pipeline: &Pipeline, stamp: Time) {
        use topics::*;
        for (m, topic) in out.tool_feedback.iter().zip(pipeline.feedback_topics()) {
            self.bag_write(&topic, Qos::SensorData, m, stamp);
        }
        if let Some(m) = &out.deformed_mesh {
            self.bag_write(DEFORMED_MESH, Qos::Latched, m, stamp);
        }
        if let Some(m) = &out.surface_marker {
            self.bag_write(SURFACE_MARKER, Qos::Latched, m, stamp);
        }
        if let Some(m) = &out.raycast {
            self.bag_write(RAYCAST_IMAGE, Qos::SensorData, m, stamp);
        }
        if let Some(m) = &out.dpcm_height {
            self.bag_write(DPCM_HEIGHT, Qos::SensorData, m, stamp);
        }
        if let Some(m) = &out.dpcm_image {
            self.bag_write(DPCM_IMAGE, Qos::SensorData, m, stamp);
        }
        let info = out.warped_volume.then(|| warped_info(pipeline, stamp)).flatten();
        if let Some(info) = &info {
            self.bag_write(WARPED_VOLUME_INFO, Qos::Latched, info, stamp);
        }
        if let Some(m) = &out.diagnostics {
            let mut m = m.clone();
            self.report_failure(&mut m);
            self.bag_write(DIAGNOSTICS, Qos::Reliable, &m, stamp);
        }
        #[cfg(feature = "rerun")]
        if let Some(log) = &self.rerun {
            log.set_time(stamp.as_secs());
            let mut logged = Ok(());
            if let Some(m) = &out.deformed_mesh {
                logged = logged.and_then(|()| log.log_mesh(m));
            }
            for (m, config) in out.tool_feedback.iter().zip(&pipeline.scene().tools) {
                logged = logged.and_then(|()| log.log_feedback(&config.name, m));
            }
            if let Some(info) = &info {
                logged = logged.and_then(|()| log.log_warped_volume(info, pipeline.scene().file_to_world));
            }
            if let (true, Some(samples), Some(grid)) =
                (out.warped_volume, pipeline.warped_samples(), pipeline.warped_grid())
            {
                logged = logged.and_then(|()| log.log_slices(samples, grid, slice_point(pipeline, grid)));
            }
            if out.raycast.is_some() {
                logged = logged.and_then(|()| log.log_camera(&pipeline.scene().camera));
            }
            for (path, image) in [
                ("world/camera/image", &out.raycast),
                ("dpcm/height", &out.dpcm_height),
                ("dpcm/image", &out.dpcm_image),
            ] {
                if let Some(image) = image {
                    logged = logged.and_then(|()| log.log_image(path, image));
                }
            }
            if let Some(m) = &out.diagnostics {
                logged = logged.and_then(|()| log.log_diagnostics(m));
            }
            if let Err(e) = logged {
                self.note_error("rerun log", e);
            }
        }
    }

    /// Adds the recording's failure, once there is one, to `diagnostics` (an ERROR status
    /// `defvol: recording`): what is published says it, as what is recorded does.
    pub fn report_failure(&self, diagnostics: &mut crate::msgs::DiagnosticArray) {
        if let Some(error) = &self.record_error {
            diagnostics.status.push(crate::msgs::DiagnosticStatus {
                level: crate::msgs::DiagnosticStatus::ERROR,
                name: "defvol: recording".into(),
                message: error.clone(),
                ..Default::default()
            });
        }
    }

    /// Closes the records; reports what each holds.
    pub fn finish(self) -> Result<(), SessionError> {
        #[cfg(feature = "rerun")]
        if let Some(log) = &self.rerun {
            log.flush()?;
        }
        #[cfg(feature = "mcap")]
        if let Some(bag) = self.bag {
            let path = bag.path().to_owned();
            match bag.finish() {
                Ok(summary) => tracing::info!(
                    "wrote {} ({} messages on {} topics)",
                    path.display(),
                    summary.messages,
                    summary.channels
                ),
                // Reported when it happened; what came before it is kept (`defvol bag recover`
                // makes the file whole).
                Err(e) if self.record_error.is_some() => {
                    tracing::warn!("{e}: the recording kept what came before (defvol bag recover makes it whole)");
                }
                Err(e) => return Err(e.into()),
            }
        }
        Ok(())
    }
}

/// Where the slices of the warped volume cross (file units): the first tool's tip, else the
/// volume's centre.
#[cfg(feature = "rerun")]
fn slice_point(pipeline: &Pipeline, grid: &crate::volume::Grid) -> nalgebra::Vector3<f64> {
    let tip = pipeline.tool_topics().first().and_then(|(pose, _)| pipeline.tool_on(pose)).map(|(_, pose)| pose);
    match tip {
        Some(pose) => pose.translation.vector / pipeline.scene().file_to_world,
        None => grid.world_from_index(grid.dims.map(|n| n.saturating_sub(1) as f64 / 2.0).into()),
    }
}

/// The `warped_volume/info` message for the pipeline's latest warp.
pub fn warped_info(pipeline: &Pipeline, stamp: Time) -> Option<crate::msgs::WarpedVolumeInfo> {
    let warped = pipeline.warped_volume()?;
    let grid = &warped.grid;
    let d = &grid.direction;
    Some(crate::msgs::WarpedVolumeInfo {
        header: crate::msgs::Header { stamp, frame_id: pipeline.scene().frame_id.clone() },
        service_name: pipeline.scene().warp.service.clone(),
        sequence: warped.sequence,
        dims: grid.dims.map(|d| d as u32),
        spacing: grid.spacing,
        origin: grid.origin,
        direction: [d[(0, 0)], d[(0, 1)], d[(0, 2)], d[(1, 0)], d[(1, 1)], d[(1, 2)], d[(2, 0)], d[(2, 1)], d[(2, 2)]],
    })
}

#[cfg(test)]
mod tests {
    use crate::session::RecordOptions;

    #[test]
    fn a_recording_whose_files_exist_is_numbered_past_them() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("k.mcap");
        let bag = dir.path().join("organ");
        let asked = RecordOptions {
            mcap: Some(file.clone()),
            rerun_file: Some(dir.path().join("k.rrd")),
            ..Default::default()
        };
        assert_eq!(asked.unused_from(0).1, 0);
        std::fs::write(&file, b"earlier").unwrap();
        std::fs::write(dir.path().join("k_1.rrd"), b"earlier").unwrap();
        // k.mcap is taken, and k_1's rerun log: the recording goes to k_2.
        let (unused, n) = asked.unused_from(0);
        assert_eq!(
            (unused.mcap.unwrap(), unused.rerun_file.unwrap(), n),
            (dir.path().join("k_2.mcap"), dir.path().join("k_2.rrd"), 2)
        );
        std::fs::create_dir(&bag).unwrap();
        let directory = RecordOptions { mcap: Some(bag), ..Default::default() };
        assert_eq!(directory.unused_from(0).0.mcap.unwrap(), dir.path().join("organ_1"));
        assert_eq!(std::fs::read(&file).unwrap(), b"earlier");
    }
}
