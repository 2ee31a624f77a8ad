//! The force loop's **local model**: multirate haptics as Çavuşoğlu & Tendick (2000) do it.
//! The full implicit solve runs at the simulation's rate; after each solve it hands the force
//! loop, for every coupled tool, the simulated tool's state and the contact it presses
//! condensed to what the tool feels: one plane along the contact force, whose stiffness is
//! the penalty in series with the mesh's compliance there, read from the solve's own
//! system (`Simulation::local_models`). The loop answers each device pose from that model at
//! its own rate, with the coupling's law and implicit step, so its cost does not grow with
//! the mesh; the next solve, which receives the same poses, brings it back in line.

use nalgebra::{Isometry3, Matrix3, Matrix6, UnitQuaternion, Vector3, Vector6};

use crate::tool::{Coupling, Friction, RotationalCoupling};

/// The contact a coupled tool presses, as the force loop sees it between two solves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalContact {
    /// Unit normal out of the surface (the direction the contact pushes the tool).
    pub normal: Vector3<f64>,
    /// (contact point - tip) × normal: how turning the tool moves it along the normal.
    pub lever: Vector3<f64>,
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
    /// Where the simulated tool was when the contact was linearised, how far it turned
    /// since (axis times angle), and the time since.
    anchor: Vector3<f64>,
    turned: Vector3<f64>,
    elapsed: f64,
}

/// A simulated tool's turning between two solves (a rotational coupling): advanced with the
/// coupling's law and the full solve's implicit step, the contact plane's row spanning it
/// through its lever; the rest of the contacts' torque (friction's, other points') held.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalTurning {
    pub coupling: RotationalCoupling,
    pub orientation: UnitQuaternion<f64>,
    pub omega: Vector3<f64>,
    /// The device's last orientation, for its angular velocity.
    pub device: UnitQuaternion<f64>,
    /// The contacts' torque on the tool about its tip at the solve that the contact plane
    /// does not carry (N·m), held.
    pub contact_torque: Vector3<f64>,
}

impl LocalTurning {
    /// The coupling's torque at the device's angular velocity `device_omega`, with its
    /// stiffness and damping (scaled when it saturates) and whether it did.
    fn twist(&self, device_omega: &Vector3<f64>) -> (Vector3<f64>, f64, f64, bool) {
        self.coupling.twist((self.device * self.orientation.inverse()).scaled_axis(), device_omega - self.omega)
    }

    /// Its row of the local step: (I + hC + h²K) Δω = h (τ + τ_held - h K ω).
    fn row(&self, device_omega: &Vector3<f64>, h: f64) -> (Matrix3<f64>, Vector3<f64>) {
        let (torque, stiffness, damping, _) = self.twist(device_omega);
        let diag = Matrix3::identity() * (self.coupling.inertia + h * damping + h * h * stiffness);
        (diag, (torque + self.contact_torque - self.omega * (h * stiffness)) * h)
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
    pub lever: Vector3<f64>,
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
                lever: c.lever,
                depth,
                stiffness,
                surface_speed: c.surface_speed,
                friction: c.friction,
            })
        });
        // The plane now carries its own torque; the rest of the contacts' is held.
        if let (Some(turning), Some(c)) = (&mut model.turning, &model.contact) {
            turning.contact_torque -= c.lever * (c.stiffness * c.depth.max(0.0));
        }
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
        Self {
            tool,
            coupling,
            position,
            velocity,
            device,
            contact,
            turning: None,
            anchor: position,
            turned: Vector3::zeros(),
            elapsed: 0.0,
        }
    }

    /// The contact's penetration with the simulated tool at `x` (turned by `turned` since
    /// the solve), `elapsed` after the solve.
    fn depth_at(&self, contact: &LocalContact, x: &Vector3<f64>, elapsed: f64) -> f64 {
        let turned = if self.turning.is_some() { contact.lever.dot(&self.turned) } else { 0.0 };
        contact.depth - contact.normal.dot(&(x - self.anchor)) - turned + contact.surface_speed * elapsed
    }

    /// Advances the simulated tool by `dt` towards the device at `device` (the implicit
    /// Euler step the full solve takes for it, the mesh condensed into the contact plane;
    /// turning too with a rotational coupling) and returns what the device feels.
    pub fn answer(&mut self, device: &Isometry3<f64>, dt: f64) -> LocalAnswer {
        let step = |now: Vector3<f64>, last: Vector3<f64>| if dt > 0.0 { (now - last) / dt } else { Vector3::zeros() };
        let device_velocity = step(device.translation.vector, self.device);
        self.device = device.translation.vector;
        let device_omega = self.turning.as_mut().map_or_else(Vector3::zeros, |t| {
            let omega = step((device.rotation * t.device.inverse()).scaled_axis(), Vector3::zeros());
            t.device = device.rotation;
            omega
        });
        if dt > 0.0 {
            let dx = self.local_step(&device_velocity, &device_omega, dt);
            self.velocity += dx.fixed_rows::<3>(0);
            self.position += self.velocity * dt;
            if let Some(t) = &mut self.turning {
                t.omega += dx.fixed_rows::<3>(3);
                t.orientation = UnitQuaternion::from_scaled_axis(t.omega * dt) * t.orientation;
                self.turned += t.omega * dt;
            }
            self.elapsed += dt;
        }
        let (pull, _, _, pulled) = self.pull(&device_velocity);
        let (torque, twisted) = self.turning.as_ref().map_or((Vector3::zeros(), false), |t| {
            let (torque, _, _, saturated) = t.twist(&device_omega);
            (-torque, saturated)
        });
        LocalAnswer { force: -pull, torque, saturated: pulled || twisted }
    }

    /// The implicit Euler step the full solve takes for the tool, its (Δv, Δω): the
    /// coupling's rows, and the contact plane's row over both (gradient (n, lever)), kept
    /// only if the tool still presses at the step's end, with its friction's damper on the
    /// sliding velocity (lagged, as in the solve).
    fn local_step(&self, device_velocity: &Vector3<f64>, device_omega: &Vector3<f64>, h: f64) -> Vector6<f64> {
        let (pull, stiffness, damping, _) = self.pull(device_velocity);
        let mut a = Matrix6::identity();
        let mut b = Vector6::zeros();
        a.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(Matrix3::identity() * (self.coupling.mass + h * damping + h * h * stiffness)));
        b.fixed_rows_mut::<3>(0).copy_from(&((pull - self.velocity * (h * stiffness)) * h));
        let omega = self.turning.as_ref().map_or_else(Vector3::zeros, |t| t.omega);
        if let Some(t) = &self.turning {
            let (diag, rhs) = t.row(device_omega, h);
            a.fixed_view_mut::<3, 3>(3, 3).copy_from(&diag);
            b.fixed_rows_mut::<3>(3).copy_from(&rhs);
        }
        let free = a.try_inverse().unwrap_or_else(Matrix6::zeros) * b;
        let Some(c) = self.contact else { return free };
        let lever = if self.turning.is_some() { c.lever } else { Vector3::zeros() };
        let gradient = Vector6::new(c.normal.x, c.normal.y, c.normal.z, lever.x, lever.y, lever.z);
        let velocity = Vector6::new(self.velocity.x, self.velocity.y, self.velocity.z, omega.x, omega.y, omega.z);
        let depth = self.depth_at(&c, &self.position, self.elapsed);
        let rate = c.surface_speed - gradient.dot(&velocity);
        let across = Matrix3::identity() - c.normal * c.normal.transpose();
        let sliding = across * self.velocity;
        let brake = c.friction.map_or(0.0, |f| f.damping(c.stiffness * depth.max(0.0), sliding.norm()));
        let mut a = a + gradient * gradient.transpose() * (h * h * c.stiffness);
        let mut b = b + gradient * (h * c.stiffness * (depth + h * rate));
        let mut braked = a.fixed_view_mut::<3, 3>(0, 0);
        braked += across * (h * brake);
        let mut braking = b.fixed_rows_mut::<3>(0);
        braking -= sliding * (h * brake);
        let pressed = a.try_inverse().unwrap_or_else(Matrix6::zeros) * b;
        match depth + h * (c.surface_speed - gradient.dot(&(velocity + pressed))) > 0.0 {
            true => pressed,
            false => free,
        }
    }

    /// The coupling's pull on the simulated tool (the full solve's law, `Coupling::pull`).
    fn pull(&self, device_velocity: &Vector3<f64>) -> (Vector3<f64>, f64, f64, bool) {
        self.coupling.pull(self.device - self.position, device_velocity - self.velocity)
    }
}
