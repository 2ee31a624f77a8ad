//! Tool inputs checked before they reach the solver: a bad message is refused with its
//! reason, counted for `diagnostics`, and the tool keeps its last good state.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::msgs::{PoseStamped, Time, WrenchStamped};

/// Limits on what a tool message may say.
#[derive(Debug, Clone, PartialEq)]
pub struct InputLimits {
    /// A pose's quaternion may be this far from unit length; nearer ones are normalised.
    pub quaternion_tolerance: f64,
    /// Largest commanded force (N) and torque (N·m) accepted.
    pub max_force: f64,
    pub max_torque: f64,
    /// Messages stamped more than this before "now" (seconds) are stale; `None` accepts any
    /// age (replay, where "now" is the bag's time).
    pub max_age: Option<f64>,
    /// Largest position magnitude (metres): beyond it a pose is surely a unit or frame error.
    pub max_position: f64,
}

impl InputLimits {
    /// These limits with the scene's `inputs` settings; where ages go unchecked (replay,
    /// whose "now" is the bag's time) they stay unchecked.
    pub fn with_scene(&self, inputs: &crate::scene::InputsConfig) -> Self {
        let max_age = self.max_age.and((inputs.max_age > 0.0).then_some(inputs.max_age));
        Self { max_age, ..self.clone() }
    }
}

impl Default for InputLimits {
    fn default() -> Self {
        Self { quaternion_tolerance: 0.01, max_force: 200.0, max_torque: 20.0, max_age: Some(0.5), max_position: 100.0 }
    }
}

/// Why a tool message was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum Rejection {
    #[error("{topic}: {field} is not finite")]
    NotFinite { topic: String, field: &'static str },
    #[error("{topic}: quaternion length {norm:.4} is not 1 (tolerance {tolerance})")]
    Quaternion { topic: String, norm: f64, tolerance: f64 },
    #[error("{topic}: position {distance:.3} m from the origin is beyond {limit} m")]
    FarAway { topic: String, distance: f64, limit: f64 },
    #[error("{topic}: {what} {magnitude:.3} exceeds the limit {limit}")]
    Absurd { topic: String, what: &'static str, magnitude: f64, limit: f64 },
    #[error("{topic}: frame `{frame}` is not the world frame `{world}`")]
    UnknownFrame { topic: String, frame: String, world: String },
    #[error("{topic}: stamp {stamp:.6} s is older than the last accepted {last:.6} s")]
    OutOfOrder { topic: String, stamp: f64, last: f64 },
    #[error("{topic}: stamp {stamp:.6} s is {age:.3} s old (limit {limit} s)")]
    Stale { topic: String, stamp: f64, age: f64, limit: f64 },
    #[error("{topic}: no such tool topic")]
    UnknownTopic { topic: String },
}

impl Rejection {
    /// A short name of the kind, for counters.
    pub fn kind(&self) -> &'static str {
        match self {
            Rejection::NotFinite { .. } => "not_finite",
            Rejection::Quaternion { .. } => "quaternion",
            Rejection::FarAway { .. } => "far_away",
            Rejection::Absurd { .. } => "absurd_wrench",
            Rejection::UnknownFrame { .. } => "unknown_frame",
            Rejection::OutOfOrder { .. } => "out_of_order",
            Rejection::Stale { .. } => "stale",
            Rejection::UnknownTopic { .. } => "unknown_topic",
        }
    }

    /// The topic the refused message came on.
    pub fn topic(&self) -> &str {
        match self {
            Rejection::NotFinite { topic, .. }
            | Rejection::Quaternion { topic, .. }
            | Rejection::FarAway { topic, .. }
            | Rejection::Absurd { topic, .. }
            | Rejection::UnknownFrame { topic, .. }
            | Rejection::OutOfOrder { topic, .. }
            | Rejection::Stale { topic, .. }
            | Rejection::UnknownTopic { topic } => topic,
        }
    }
}

/// Counts of accepted and refused inputs, and the last refusal.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InputCounters {
    pub accepted: u64,
    pub rejected: BTreeMap<&'static str, u64>,
    pub last_rejection: Option<String>,
    /// When each (topic, reason) was last logged.
    logged: BTreeMap<(String, &'static str), std::time::Instant>,
}

impl InputCounters {
    /// Counts `outcome`; a refusal is also logged at WARN, at most once a second per topic
    /// and reason (as `RCLCPP_WARN_THROTTLE` does), so a flood of bad input cannot drown the
    /// log while the first of each kind is always seen.
    pub fn record(&mut self, outcome: &Result<(), Rejection>) {
        match outcome {
            Ok(()) => self.accepted += 1,
            Err(rejection) => {
                *self.rejected.entry(rejection.kind()).or_default() += 1;
                self.last_rejection = Some(rejection.to_string());
                let now = std::time::Instant::now();
                let key = (rejection.topic().to_owned(), rejection.kind());
                if self.logged.get(&key).is_none_or(|at| now.duration_since(*at).as_secs_f64() >= 1.0) {
                    tracing::warn!("refused {rejection} (more like it within a second are only counted)");
                    self.logged.insert(key, now);
                }
            }
        }
    }
    pub fn total_rejected(&self) -> u64 {
        self.rejected.values().sum()
    }
}

/// The checks shared by poses and wrenches: frame and stamp order.
pub struct Checker<'a> {
    pub limits: &'a InputLimits,
    pub world_frame: &'a str,
    pub now: Time,
}

impl Checker<'_> {
    fn frame_and_stamp(&self, topic: &str, frame: &str, stamp: Time, last: Option<Time>) -> Result<(), Rejection> {
        if !(frame.is_empty() || frame == self.world_frame) {
            return Err(Rejection::UnknownFrame {
                topic: topic.into(),
                frame: frame.into(),
                world: self.world_frame.into(),
            });
        }
        if let Some(last) = last.filter(|last| stamp < *last) {
            return Err(Rejection::OutOfOrder { topic: topic.into(), stamp: stamp.as_secs(), last: last.as_secs() });
        }
        if let Some(limit) = self.limits.max_age {
            let age = self.now.as_secs() - stamp.as_secs();
            if age > limit {
                return Err(Rejection::Stale { topic: topic.into(), stamp: stamp.as_secs(), age, limit });
            }
        }
        Ok(())
    }

    /// A pose as `world_from_tool`, or why not; `stamp` is the one its age and order are
    /// judged by (its own, or the time it came for a zero stamp).
    pub fn pose(
        &self,
        topic: &str,
        msg: &PoseStamped,
        stamp: Time,
        last: Option<Time>,
    ) -> Result<Isometry3<f64>, Rejection> {
        let (p, q) = (msg.pose.position, msg.pose.orientation);
        if ![p.x, p.y, p.z].iter().all(|v| v.is_finite()) {
            return Err(Rejection::NotFinite { topic: topic.into(), field: "pose.position" });
        }
        if ![q.x, q.y, q.z, q.w].iter().all(|v| v.is_finite()) {
            return Err(Rejection::NotFinite { topic: topic.into(), field: "pose.orientation" });
        }
        let quaternion = Quaternion::new(q.w, q.x, q.y, q.z);
        let norm = quaternion.norm();
        if (norm - 1.0).abs() > self.limits.quaternion_tolerance {
            return Err(Rejection::Quaternion {
                topic: topic.into(),
                norm,
                tolerance: self.limits.quaternion_tolerance,
            });
        }
        let position = Vector3::new(p.x, p.y, p.z);
        if position.norm() > self.limits.max_position {
            return Err(Rejection::FarAway {
                topic: topic.into(),
                distance: position.norm(),
                limit: self.limits.max_position,
            });
        }
        self.frame_and_stamp(topic, &msg.header.frame_id, stamp, last)?;
        Ok(Isometry3::from_parts(Translation3::from(position), UnitQuaternion::from_quaternion(quaternion)))
    }

    /// A wrench's force (N, world), or why not; `stamp` as for [`Checker::pose`].
    pub fn wrench(
        &self,
        topic: &str,
        msg: &WrenchStamped,
        stamp: Time,
        last: Option<Time>,
    ) -> Result<Vector3<f64>, Rejection> {
        let (force, torque): (Vector3<f64>, Vector3<f64>) = (msg.wrench.force.into(), msg.wrench.torque.into());
        if !force.iter().all(|v| v.is_finite()) {
            return Err(Rejection::NotFinite { topic: topic.into(), field: "wrench.force" });
        }
        if !torque.iter().all(|v| v.is_finite()) {
            return Err(Rejection::NotFinite { topic: topic.into(), field: "wrench.torque" });
        }
        if force.norm() > self.limits.max_force {
            return Err(Rejection::Absurd {
                topic: topic.into(),
                what: "force (N)",
                magnitude: force.norm(),
                limit: self.limits.max_force,
            });
        }
        if torque.norm() > self.limits.max_torque {
            return Err(Rejection::Absurd {
                topic: topic.into(),
                what: "torque (N·m)",
                magnitude: torque.norm(),
                limit: self.limits.max_torque,
            });
        }
        self.frame_and_stamp(topic, &msg.header.frame_id, stamp, last)?;
        Ok(force)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Pose};

    fn pose(x: f64, q: [f64; 4], frame: &str, t: f64) -> PoseStamped {
        let mut msg =
            PoseStamped { header: Header { stamp: Time::from_secs(t), frame_id: frame.into() }, pose: Pose::default() };
        msg.pose.position.x = x;
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z, msg.pose.orientation.w) =
            (q[0], q[1], q[2], q[3]);
        msg
    }

    #[test]
    fn bad_poses_are_refused_with_their_reason() {
        let limits = InputLimits::default();
        let check = Checker { limits: &limits, world_frame: "world", now: Time::from_secs(10.0) };
        let unit = [0.0, 0.0, 0.0, 1.0];
        let iso = check
            .pose("tool_pose", &pose(0.5, [0.0, 0.0, 0.0, 1.004], "world", 10.0), Time::from_secs(10.0), None)
            .unwrap();
        assert!((iso.rotation.quaternion().norm() - 1.0).abs() < 1e-12, "near-unit quaternions are normalised");
        assert_eq!(iso.translation.vector.x, 0.5);
        let kind = |msg: PoseStamped, last: Option<f64>| {
            check.pose("tool_pose", &msg, msg.header.stamp, last.map(Time::from_secs)).unwrap_err().kind()
        };
        assert_eq!(kind(pose(f64::NAN, unit, "world", 10.0), None), "not_finite");
        assert_eq!(kind(pose(0.0, [0.0, 0.0, f64::INFINITY, 1.0], "world", 10.0), None), "not_finite");
        assert_eq!(kind(pose(0.0, [0.0, 0.0, 0.0, 2.0], "world", 10.0), None), "quaternion");
        assert_eq!(kind(pose(1e6, unit, "world", 10.0), None), "far_away");
        assert_eq!(kind(pose(0.0, unit, "camera", 10.0), None), "unknown_frame");
        assert_eq!(kind(pose(0.0, unit, "world", 9.0), Some(9.5)), "out_of_order");
        assert_eq!(kind(pose(0.0, unit, "world", 8.0), None), "stale");
        // An empty frame means the world; a stamp equal to the last is in order.
        assert!(check
            .pose("tool_pose", &pose(0.0, unit, "", 9.8), Time::from_secs(9.8), Some(Time::from_secs(9.8)))
            .is_ok());
        let message = check
            .pose("a/tool_pose", &pose(0.0, [0.0, 0.0, 0.0, 2.0], "world", 10.0), Time::from_secs(10.0), None)
            .unwrap_err()
            .to_string();
        assert!(message.contains("a/tool_pose") && message.contains("2.0000"), "{message}");
    }

    #[test]
    fn absurd_wrenches_are_refused() {
        let limits = InputLimits { max_age: None, ..Default::default() };
        let check = Checker { limits: &limits, world_frame: "world", now: Time::default() };
        let mut msg = WrenchStamped::default();
        msg.wrench.force.z = -3.0;
        assert_eq!(check.wrench("w", &msg, msg.header.stamp, None).unwrap(), Vector3::new(0.0, 0.0, -3.0));
        msg.wrench.force.z = -1e5;
        assert_eq!(check.wrench("w", &msg, msg.header.stamp, None).unwrap_err().kind(), "absurd_wrench");
        msg.wrench.force.z = 0.0;
        msg.wrench.torque.x = f64::NAN;
        assert_eq!(check.wrench("w", &msg, msg.header.stamp, None).unwrap_err().kind(), "not_finite");
        let mut counters = InputCounters::default();
        counters.record(&Ok(()));
        counters.record(&check.wrench("w", &msg, msg.header.stamp, None).map(drop));
        assert_eq!((counters.accepted, counters.total_rejected()), (1, 1));
        assert!(counters.last_rejection.unwrap().contains("wrench.torque"));
    }
}
