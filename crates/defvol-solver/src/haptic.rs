//! The force loop's **local model**: multirate haptics as Çavuşoğlu & Tendick (2000) do it.
//! The full implicit solve runs at the simulation's rate; after each solve it hands the force
//! loop, for every coupled tool, the simulated tool's state and the contact it presses
//! condensed to what the tool feels: one plane along the contact force, whose stiffness is
//! the penalty in series with the mesh's compliance there, read from the solve's own
//! system (`Simulation::local_models`). The loop answers each device pose from that model at
//! its own rate, with the coupling's law and implicit step, so its cost does not grow with
//! the mesh; the next solve, which receives the same poses, brings it back in line.

use nalgebra::{Isometry3, Matrix3, UnitQuaternion, Vector3};

use crate::tool::{Coupling, Friction, RotationalCoupling};

/// The contact a coupled tool presses, as the force loop sees it between two solves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalContact {
    /// Unit normal out of the surface (the direction the contact pushes the tool).
    pub normal: Vector3<f64>,
    /// Penetration at the solve (m); negative for a surface the tool is about to touch.
    pub depth: f64,
    /// Stiffness the tool feels along `normal` (N/m).
    pub stiffness: f64,
    /// How fast the surface there moves along `normal` at the solve (m/s): a dent deepening
    /// under the tool moves away from it.
    pub surface_speed: f64,
    /// The tool's friction against the surface (its damper on the sliding velocity, the
    /// surface held still between solves).
    pub friction: Option<Friction>,
}

/// One coupled tool's model between two solves.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalModel {
    pub tool: usize,
    pub coupling: Coupling,
    /// The simulated tool (m, m/s), advanced by each answer.
    pub position: Vector3<f64>,
    pub velocity: Vector3<f64>,
    /// The device's last position, for its velocity.
    pub device: Vector3<f64>,
    pub contact: Option<LocalContact>,
    /// With a rotational coupling, how the simulated tool turns between solves.
    pub turning: Option<LocalTurning>,
    /// Where the simulated tool was when the contact was linearised, and the time since.
    anchor: Vector3<f64>,
    elapsed: f64,
}

/// A simulated tool's turning between two solves (a rotational coupling): advanced with the
/// coupling's law and the full solve's implicit step, the contacts' torque of the last solve
/// held (the contacts' rotational stiffness is left to the next solve).
#[derive(Debug, Clone, PartialEq)]
pub struct LocalTurning {
    pub coupling: RotationalCoupling,
    pub orientation: UnitQuaternion<f64>,
    pub omega: Vector3<f64>,
    /// The device's last orientation, for its angular velocity.
    pub device: UnitQuaternion<f64>,
    /// The contacts' torque on the tool about its tip at the solve (N·m).
    pub contact_torque: Vector3<f64>,
}

impl LocalTurning {
    /// Advances by `dt` towards the device at `device`; the torque the device feels and
    /// whether the coupling saturated.
    fn answer(&mut self, device: UnitQuaternion<f64>, dt: f64) -> (Vector3<f64>, bool) {
        let device_omega =
            if dt > 0.0 { (device * self.device.inverse()).scaled_axis() / dt } else { Vector3::zeros() };
        self.device = device;
        let twist =
            |t: &Self| t.coupling.twist((t.device * t.orientation.inverse()).scaled_axis(), device_omega - t.omega);
        if dt > 0.0 {
            let (torque, stiffness, damping, _) = twist(self);
            let h = dt;
            let diag = self.coupling.inertia + h * damping + h * h * stiffness;
            self.omega += (torque + self.contact_torque - self.omega * (h * stiffness)) * (h / diag);
            self.orientation = UnitQuaternion::from_scaled_axis(self.omega * h) * self.orientation;
        }
        let (torque, _, _, saturated) = twist(self);
        (-torque, saturated)
    }
}

/// What the device feels: the coupling's pull on it (N) and, with a rotational coupling,
/// its torque (N·m), and whether either saturated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalAnswer {
    pub force: Vector3<f64>,
    pub torque: Vector3<f64>,
    pub saturated: bool,
}

/// A coupled tool's local model before the one number it may need of the step's system,
/// bᵀA⁻¹b along `along()` (the CPU and the GPU each solve it on their own system).
#[derive(Debug, Clone)]
pub(crate) struct LocalQuery {
    model: LocalModel,
    contact: Option<PendingContact>,
}

/// The contact of a local model, short of its stiffness.
#[derive(Debug, Clone)]
pub(crate) struct PendingContact {
    pub normal: Vector3<f64>,
    pub surface_speed: f64,
    pub friction: Option<Friction>,
    /// Rows and directions b of the system whose bᵀA⁻¹b the stiffness needs (none: it
    /// needs nothing).
    pub along: Vec<(usize, Vector3<f64>)>,
    pub rule: StiffnessRule,
}

/// How the contact's stiffness follows from c = bᵀA⁻¹b (A the step's system, h its step).
#[derive(Debug, Clone, Copy)]
pub(crate) enum StiffnessRule {
    /// About to touch: the penalty in series with the mesh's compliance h²c there.
    InSeries { depth: f64, penalty: f64 },
    /// Pressed through the simulated tool's row: the stiffness the tool feels along the
    /// normal, (1/c minus its own row) / h², at most the penalty; the depth from the force.
    Condensed { force: f64, own: f64, penalty: f64 },
    /// Touching without the tool's row in the system: the penalty.
    Penalty { force: f64, penalty: f64 },
}

impl LocalQuery {
    pub(crate) fn new(
        tool: usize,
        coupling: Coupling,
        position: Vector3<f64>,
        velocity: Vector3<f64>,
        device: Vector3<f64>,
        contact: Option<PendingContact>,
        turning: Option<LocalTurning>,
    ) -> Self {
        let mut model = LocalModel::new(tool, coupling, position, velocity, device, None);
        model.turning = turning;
        Self { model, contact }
    }

    /// The rows and directions b whose bᵀA⁻¹b `finish` needs, if any.
    pub(crate) fn along(&self) -> Option<&[(usize, Vector3<f64>)]> {
        self.contact.as_ref().map(|c| c.along.as_slice()).filter(|b| !b.is_empty())
    }

    /// The model, given c = bᵀA⁻¹b (ignored when `along` is none) and the step h.
    pub(crate) fn finish(self, compliance: f64, h: f64) -> LocalModel {
        let mut model = self.model;
        model.contact = self.contact.and_then(|c| {
            let (depth, stiffness) = match c.rule {
                StiffnessRule::InSeries { depth, penalty } => {
                    (depth, 1.0 / (1.0 / penalty + (h * h * compliance).max(0.0)))
                }
                StiffnessRule::Condensed { force, own, penalty } => {
                    let stiffness = ((1.0 / compliance - own) / (h * h)).clamp(0.0, penalty);
                    (force / stiffness, stiffness)
                }
                StiffnessRule::Penalty { force, penalty } => (force / penalty, penalty),
            };
            (stiffness > 0.0).then_some(LocalContact {
                normal: c.normal,
                depth,
                stiffness,
                surface_speed: c.surface_speed,
                friction: c.friction,
            })
        });
        model
    }
}

impl LocalModel {
    pub fn new(
        tool: usize,
        coupling: Coupling,
        position: Vector3<f64>,
        velocity: Vector3<f64>,
        device: Vector3<f64>,
        contact: Option<LocalContact>,
    ) -> Self {
        Self { tool, coupling, position, velocity, device, contact, turning: None, anchor: position, elapsed: 0.0 }
    }

    /// The contact's penetration with the simulated tool at `x`, `elapsed` after the solve.
    fn depth_at(&self, contact: &LocalContact, x: &Vector3<f64>, elapsed: f64) -> f64 {
        contact.depth - contact.normal.dot(&(x - self.anchor)) + contact.surface_speed * elapsed
    }

    /// Advances the simulated tool by `dt` towards the device at `device` (the implicit
    /// Euler step the full solve takes for it, the mesh condensed into the contact plane;
    /// turning too with a rotational coupling) and returns what the device feels.
    pub fn answer(&mut self, device: &Isometry3<f64>, dt: f64) -> LocalAnswer {
        let (torque, twisted) = match &mut self.turning {
            Some(turning) => turning.answer(device.rotation, dt),
            None => (Vector3::zeros(), false),
        };
        let answer = self.follow(device.translation.vector, dt);
        LocalAnswer { torque, saturated: answer.saturated || twisted, ..answer }
    }

    /// The translational part of `answer`.
    fn follow(&mut self, device: Vector3<f64>, dt: f64) -> LocalAnswer {
        let device_velocity = if dt > 0.0 { (device - self.device) / dt } else { Vector3::zeros() };
        self.device = device;
        if dt > 0.0 {
            let (pull, stiffness, damping, _) = self.pull(&device_velocity);
            let h = dt;
            let base = Matrix3::identity() * (self.coupling.mass + h * damping + h * h * stiffness);
            let free = (pull - self.velocity * (h * stiffness)) * h;
            let mut dv = base.try_inverse().unwrap_or_else(Matrix3::zeros) * free;
            if let Some(c) = self.contact {
                // The contact's row, kept only if the tool still presses at the step's end,
                // with its friction's damper on the sliding velocity (lagged, as in the solve).
                let depth = self.depth_at(&c, &self.position, self.elapsed);
                let rate = c.surface_speed - c.normal.dot(&self.velocity);
                let across = Matrix3::identity() - c.normal * c.normal.transpose();
                let sliding = across * self.velocity;
                let brake = c.friction.map_or(0.0, |f| f.damping(c.stiffness * depth.max(0.0), sliding.norm()));
                let a = base + c.normal * c.normal.transpose() * (h * h * c.stiffness) + across * (h * brake);
                let b = free + c.normal * (h * c.stiffness * (depth + h * rate)) - sliding * (h * brake);
                let pressed = a.try_inverse().unwrap_or_else(Matrix3::zeros) * b;
                if depth + h * (c.surface_speed - c.normal.dot(&(self.velocity + pressed))) > 0.0 {
                    dv = pressed;
                }
            }
            self.velocity += dv;
            self.position += self.velocity * h;
            self.elapsed += h;
        }
        let (pull, _, _, saturated) = self.pull(&device_velocity);
        LocalAnswer { force: -pull, torque: Vector3::zeros(), saturated }
    }

    /// The coupling's pull on the simulated tool (the full solve's law, `Coupling::pull`).
    fn pull(&self, device_velocity: &Vector3<f64>) -> (Vector3<f64>, f64, f64, bool) {
        self.coupling.pull(self.device - self.position, device_velocity - self.velocity)
    }
}
