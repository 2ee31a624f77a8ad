//! Rigid tools touching the mesh. Contact is a **penalty** `k_c · depth`, against the
//! boundary surface (`contact.rs`, the default: tools thinner than the mesh spacing are
//! felt) or against every node inside the shape (`ContactModel::Nodes`, what the GPU
//! kernels do); the implicit solver takes its Jacobian into the system, so stiff contact
//! stays stable at large steps. A tool may follow its device through a **virtual
//! coupling** (a spring-damper, as haptics frameworks render stiff contact): the simulated
//! tool is then a body of the implicit system and the device feels the coupling force.
//! A commanded force (from a wrench topic) is spread over the nodes near the tool tip.

use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use super::contact::ContactParams;

/// Tool geometry in the tool frame. The tool frame's origin is the tip; a capsule's
/// shaft runs from the tip along +z (towards the handle).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum ToolShape {
    Sphere { radius: f64 },
    Capsule { radius: f64, length: f64 },
}

impl ToolShape {
    pub fn radius(&self) -> f64 {
        match self {
            ToolShape::Sphere { radius } | ToolShape::Capsule { radius, .. } => *radius,
        }
    }
    /// Shaft length (0 for a sphere): the core segment runs tip → tip + length·z.
    pub fn length(&self) -> f64 {
        match self {
            ToolShape::Sphere { .. } => 0.0,
            ToolShape::Capsule { length, .. } => *length,
        }
    }
}

/// What a tool's contact acts on.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ContactModel {
    /// The boundary surface: faces, edges and nodes, by barycentric weights.
    #[default]
    Surface,
    /// Every node inside the shape, one by one (tools wider than the mesh spacing).
    Nodes,
}

/// A spring-damper between the device's commanded pose and the simulated tool, which the
/// contact stops at the surface. The device feels the coupling force, never more than
/// `max_force`: a pose that jumps through the organ pulls the tool with that force at most.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Coupling {
    /// N/m.
    pub stiffness: f64,
    /// N·s/m.
    pub damping: f64,
    /// Mass of the simulated tool (kg).
    pub mass: f64,
    /// Largest coupling spring force (N).
    pub max_force: f64,
}

impl Coupling {
    /// The pull on the simulated tool, `offset` (device minus tool) and `relative_velocity`
    /// away from the device, with the stiffness and damping that make it: scaled down
    /// together when the pull would pass `max_force`, which the last element says.
    pub fn pull(&self, offset: Vector3<f64>, relative_velocity: Vector3<f64>) -> (Vector3<f64>, f64, f64, bool) {
        saturating(offset, relative_velocity, self.stiffness, self.damping, self.max_force)
    }

    pub fn validate(&self, index: usize) -> Result<(), super::SolverError> {
        let why = "must be finite and positive (damping may be 0)";
        check_fields(
            index,
            "coupling",
            &[
                ("stiffness", self.stiffness, self.stiffness > 0.0, why),
                ("damping", self.damping, self.damping >= 0.0, why),
                ("mass", self.mass, self.mass > 0.0, why),
                ("max_force", self.max_force, self.max_force > 0.0, why),
            ],
        )
    }
}

/// A spring-damper's response k·offset + c·rate, with k and c scaled down together when it
/// would pass `limit` (which the last element says): the law of both couplings.
fn saturating(
    offset: Vector3<f64>,
    rate: Vector3<f64>,
    stiffness: f64,
    damping: f64,
    limit: f64,
) -> (Vector3<f64>, f64, f64, bool) {
    let raw = offset * stiffness + rate * damping;
    let magnitude = raw.norm();
    if magnitude > limit {
        let scale = limit / magnitude;
        (raw * scale, stiffness * scale, damping * scale, true)
    } else {
        (raw, stiffness, damping, false)
    }
}

/// The first of `checks` (field, value, whether it is allowed, why) whose value is not
/// finite or not allowed, as an error naming `tools[index].section.field`.
fn check_fields(index: usize, section: &str, checks: &[(&str, f64, bool, &str)]) -> Result<(), super::SolverError> {
    match checks.iter().find(|(_, value, ok, _)| !(value.is_finite() && *ok)) {
        Some((field, value, _, why)) => Err(super::SolverError::BadParameter {
            name: format!("tools[{index}].{section}.{field}"),
            value: *value,
            why: (*why).into(),
        }),
        None => Ok(()),
    }
}

/// A torsional spring-damper between the device's orientation and the simulated tool's,
/// beside a `Coupling`: contacts along the tool turn it about its tip, and the device feels
/// the torque that holds it, never more than `max_torque`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotationalCoupling {
    /// N·m/rad.
    pub stiffness: f64,
    /// N·m·s/rad.
    pub damping: f64,
    /// The simulated tool's moment of inertia about its tip (kg·m²).
    pub inertia: f64,
    /// Largest coupling torque (N·m).
    pub max_torque: f64,
}

impl RotationalCoupling {
    /// The torque on the simulated tool for the device turned `error` (axis times angle)
    /// from it and `relative_omega` faster, with the stiffness and damping that make it,
    /// scaled down together past `max_torque` (which the last element says).
    pub fn twist(&self, error: Vector3<f64>, relative_omega: Vector3<f64>) -> (Vector3<f64>, f64, f64, bool) {
        saturating(error, relative_omega, self.stiffness, self.damping, self.max_torque)
    }

    pub fn validate(&self, index: usize) -> Result<(), super::SolverError> {
        let why = "must be finite and positive (damping may be 0)";
        check_fields(
            index,
            "rotational_coupling",
            &[
                ("stiffness", self.stiffness, self.stiffness > 0.0, why),
                ("damping", self.damping, self.damping >= 0.0, why),
                ("inertia", self.inertia, self.inertia > 0.0, why),
                ("max_torque", self.max_torque, self.max_torque > 0.0, why),
            ],
        )
    }
}

/// Coulomb friction between a tool and the surface it touches, regularised as the implicit
/// step needs it (after IPC's lagged friction): the normal force and the sliding speed are
/// those at the step's start, and the tangential force is a damper on the sliding velocity
/// at the step's end, μ N / max(speed, stick_speed). Below `stick_speed` the tool sticks,
/// held up to μ_s N; sliding, it is braked by μ_k N.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Friction {
    /// μ_s: the largest tangential force while sticking, per unit normal force.
    #[serde(rename = "static")]
    pub static_coefficient: f64,
    /// μ_k: the tangential force while sliding, per unit normal force (at most μ_s).
    #[serde(rename = "kinetic")]
    pub kinetic_coefficient: f64,
    /// Sliding speeds below this count as sticking (m/s).
    #[serde(default = "Friction::default_stick_speed")]
    pub stick_speed: f64,
}

impl Friction {
    /// 0.1 mm/s: a tool held against a sideways load at a third of the static limit creeps
    /// at a third of it.
    fn default_stick_speed() -> f64 {
        1e-4
    }

    /// The damping coefficient (N·s/m) of the tangential damper at normal force `normal` (N)
    /// and sliding speed `speed` (m/s): sticking below `stick_speed`, sliding above.
    pub fn damping(&self, normal: f64, speed: f64) -> f64 {
        match speed < self.stick_speed {
            true => self.static_coefficient * normal / self.stick_speed,
            false => self.kinetic_coefficient * normal / speed,
        }
    }

    pub fn validate(&self, index: usize) -> Result<(), super::SolverError> {
        let (s, k) = (self.static_coefficient, self.kinetic_coefficient);
        check_fields(
            index,
            "friction",
            &[
                ("kinetic", k, k >= 0.0, "must be finite and not negative"),
                ("static", s, s >= k, "must be finite and at least the kinetic coefficient"),
                ("stick_speed", self.stick_speed, self.stick_speed > 0.0, "must be finite and positive (m/s)"),
            ],
        )
    }
}

/// A tool's state for one step, in world coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct Tool {
    pub shape: ToolShape,
    pub world_from_tool: Isometry3<f64>,
    /// Force the user commands through the tool (N, world frame), spread near the tip.
    pub applied_force: Vector3<f64>,
    /// Radius of the neighbourhood over which `applied_force` is spread (m).
    pub spread_radius: f64,
    pub contact_stiffness: f64,
    pub contact: ContactModel,
    /// With a coupling, `world_from_tool` is the device's pose and the simulated tool
    /// follows it; without one, the tool is where the device is.
    pub coupling: Option<Coupling>,
    /// Friction against the surface (surface contact); none: frictionless.
    pub friction: Option<Friction>,
    /// With a `coupling`, the simulated tool also turns, held to the device's orientation.
    pub rotational_coupling: Option<RotationalCoupling>,
}

impl Tool {
    pub fn new(shape: ToolShape, contact_stiffness: f64) -> Self {
        Self {
            shape,
            world_from_tool: Isometry3::identity(),
            applied_force: Vector3::zeros(),
            spread_radius: shape.radius() * 2.0,
            contact_stiffness,
            contact: ContactModel::Surface,
            coupling: None,
            friction: None,
            rotational_coupling: None,
        }
    }

    pub fn tip(&self) -> Vector3<f64> {
        self.world_from_tool.translation.vector
    }

    /// World-space core segment (a, b) of the shape; a == b for a sphere.
    pub fn segment(&self) -> (Vector3<f64>, Vector3<f64>) {
        let a = self.world_from_tool * Point3::origin();
        let b = self.world_from_tool * Point3::new(0.0, 0.0, self.shape.length());
        (a.coords, b.coords)
    }

    /// GPU/CPU shared description: segment ends, radius, stiffness.
    pub fn contact_params(&self) -> ContactParams {
        let (a, b) = self.segment();
        ContactParams { a, b, radius: self.shape.radius(), stiffness: self.contact_stiffness }
    }
}

/// Weights (summing to 1) with which a force at `tip` is spread over the nodes within
/// `radius`: w ∝ (1 - d/r)², or the single nearest node if none is that close.
pub fn spread_weights(nodes: &[Vector3<f64>], tip: &Vector3<f64>, radius: f64) -> Vec<(u32, f64)> {
    let mut w: Vec<(u32, f64)> = nodes
        .iter()
        .enumerate()
        .filter_map(|(i, p)| {
            let d = (p - tip).norm();
            (d < radius).then(|| (i as u32, (1.0 - d / radius).powi(2)))
        })
        .filter(|(_, w)| *w > 0.0)
        .collect();
    if w.is_empty() {
        let nearest =
            nodes.iter().enumerate().min_by(|a, b| (a.1 - tip).norm_squared().total_cmp(&(b.1 - tip).norm_squared()));
        if let Some((i, _)) = nearest {
            w.push((i as u32, 1.0));
        }
    }
    let total: f64 = w.iter().map(|(_, w)| w).sum();
    for (_, x) in &mut w {
        *x /= total;
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capsule_contact_pushes_out_along_the_normal() {
        let mut tool = Tool::new(ToolShape::Capsule { radius: 0.01, length: 0.1 }, 1000.0);
        tool.world_from_tool = Isometry3::translation(0.0, 0.0, 0.05);
        let c = tool.contact_params();
        let (f, n) = c.contact(&Vector3::new(0.004, 0.0, 0.1)).unwrap();
        assert!((n - Vector3::x()).norm() < 1e-12);
        assert!((f.x - 1000.0 * 0.006).abs() < 1e-12);
        assert!(c.contact(&Vector3::new(0.02, 0.0, 0.1)).is_none());
        // Beyond the tip: hemispherical cap around the tip.
        let (_, n) = c.contact(&Vector3::new(0.0, 0.0, 0.045)).unwrap();
        assert!((n + Vector3::z()).norm() < 1e-12);
    }

    /// Impossible friction is refused naming the field; sticking and sliding follow
    /// Coulomb: μ_s N at the stick speed, μ_k N sliding faster.
    #[test]
    fn friction_is_checked_and_follows_coulomb() {
        let friction = Friction { static_coefficient: 0.5, kinetic_coefficient: 0.3, stick_speed: 1e-4 };
        assert!(friction.validate(0).is_ok());
        for (bad, field) in [
            (Friction { static_coefficient: 0.2, ..friction }, "tools[2].friction.static"),
            (Friction { kinetic_coefficient: f64::NAN, ..friction }, "tools[2].friction.kinetic"),
            (Friction { stick_speed: 0.0, ..friction }, "tools[2].friction.stick_speed"),
        ] {
            let e = bad.validate(2).unwrap_err().to_string();
            assert!(e.contains(field), "{e}");
        }
        let normal = 4.0;
        assert!((friction.damping(normal, 0.5e-4) * 1e-4 - 0.5 * normal).abs() < 1e-12);
        assert!((friction.damping(normal, 0.02) * 0.02 - 0.3 * normal).abs() < 1e-12);
    }

    /// Impossible rotational coupling is refused naming its own fields.
    #[test]
    fn rotational_coupling_is_checked_by_its_own_names() {
        let good = RotationalCoupling { stiffness: 2.0, damping: 0.02, inertia: 1e-5, max_torque: 1.0 };
        assert!(good.validate(0).is_ok());
        for (bad, field) in [
            (RotationalCoupling { inertia: 0.0, ..good }, "tools[1].rotational_coupling.inertia"),
            (RotationalCoupling { max_torque: -1.0, ..good }, "tools[1].rotational_coupling.max_torque"),
            (RotationalCoupling { stiffness: f64::INFINITY, ..good }, "tools[1].rotational_coupling.stiffness"),
            (RotationalCoupling { damping: -0.1, ..good }, "tools[1].rotational_coupling.damping"),
        ] {
            let e = bad.validate(1).unwrap_err().to_string();
            assert!(e.contains(field), "{e}");
        }
    }

    #[test]
    fn spread_weights_sum_to_one() {
        let nodes: Vec<_> = (0..10).map(|i| Vector3::new(i as f64 * 0.01, 0.0, 0.0)).collect();
        let w = spread_weights(&nodes, &Vector3::new(0.02, 0.0, 0.0), 0.025);
        assert_eq!(w.len(), 5);
        assert!((w.iter().map(|x| x.1).sum::<f64>() - 1.0).abs() < 1e-12);
        let far = spread_weights(&nodes, &Vector3::new(1.0, 0.0, 0.0), 0.01);
        assert_eq!(far, vec![(9, 1.0)]);
    }
}
