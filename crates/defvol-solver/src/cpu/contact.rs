//! Tools against the mesh in the solver: node and surface contacts found each step, their
//! rows in the implicit system, coupled tools' proxies following their devices, and the
//! forces the tools spread on the nodes.

use super::*;

impl<T: Real> Simulation<T> {
    /// Checks every tool; returns those whose contact acts node by node (the kernels').
    pub(super) fn contact_tools(&self) -> Result<Vec<ContactTool<T>>, SolverError> {
        for (index, tool) in self.tools.iter().enumerate() {
            let c = tool.contact_params();
            if !(c.a.iter().chain(c.b.iter()).all(|v| v.is_finite())) {
                return Err(SolverError::NonFiniteToolInput { index, what: "pose" });
            }
            if let Some(coupling) = &tool.coupling {
                coupling.validate(index)?;
                let why = if tool.contact != ContactModel::Surface {
                    Some("a coupled tool needs surface contact")
                } else if self.params.integrator != Integrator::ImplicitEuler {
                    Some("a coupled tool needs the implicit_euler integrator")
                } else {
                    None
                };
                if let Some(why) = why {
                    return Err(SolverError::BadParameter {
                        name: format!("tools[{index}].coupling"),
                        value: coupling.stiffness,
                        why: why.into(),
                    });
                }
            }
        }
        self.tools
            .iter()
            .filter(|tool| tool.contact == ContactModel::Nodes)
            .map(|tool| {
                let c = tool.contact_params();
                Ok(ContactTool {
                    a: c.a.map(T::of),
                    b: c.b.map(T::of),
                    radius: T::of(c.radius),
                    stiffness: T::of(c.stiffness),
                })
            })
            .collect()
    }

    /// Spreads every tool's commanded force over the nodes near its tip.
    pub(super) fn spread_external_forces(&mut self) -> Result<(), SolverError> {
        self.external.iter_mut().for_each(|f| *f = Vector3::zeros());
        for (index, tool) in self.tools.iter().enumerate() {
            if !tool.applied_force.iter().all(|f| f.is_finite()) {
                return Err(SolverError::NonFiniteToolInput { index, what: "applied force" });
            }
            if tool.applied_force == Vector3::zeros() {
                continue;
            }
            let nodes = self.positions_f64();
            for (i, w) in spread_weights(&nodes, &tool.tip(), tool.spread_radius) {
                self.external[i as usize] += (tool.applied_force * w).map(T::of);
            }
        }
        Ok(())
    }

    /// One simulated tool per coupled tool (made at the device when it first appears), the
    /// devices' velocities from their last poses, and the solver vectors sized to match.
    pub(super) fn follow_devices(&mut self) {
        let coupled: Vec<usize> = (0..self.tools.len()).filter(|&i| self.tools[i].coupling.is_some()).collect();
        if !self.proxies.iter().map(|p| p.tool).eq(coupled.iter().copied()) {
            self.proxies = coupled
                .iter()
                .map(|&tool| {
                    let tip = self.tools[tool].tip();
                    Proxy { tool, x: tip, v: Vector3::zeros(), device: tip, device_velocity: Vector3::zeros() }
                })
                .collect();
            let rows = self.u.len() + self.proxies.len();
            self.rhs.resize(rows, Vector3::zeros());
            self.precond.resize(rows, Matrix3::zeros());
            for w in [&mut self.dv, &mut self.dv_previous, &mut self.r, &mut self.z, &mut self.p, &mut self.q] {
                w.resize(rows, Vector3::zeros());
            }
            self.proxy_diag = vec![Matrix3::zeros(); self.proxies.len()];
        }
        let dt = self.params.dt;
        for p in &mut self.proxies {
            let tip = self.tools[p.tool].tip();
            p.device_velocity = (tip - p.device) / dt;
            p.device = tip;
        }
    }

    /// The surface contacts of the surface-contact tools at the current positions; with
    /// `speculative`, those about to begin too (within half the radius or spacing).
    pub(super) fn detect_contacts(&mut self, speculative: bool) -> Vec<SurfaceContact> {
        let cores: Vec<ToolCore> = (self.tools.iter().enumerate())
            .filter(|(_, tool)| tool.contact == ContactModel::Surface && tool.contact_stiffness > 0.0)
            .map(|(index, tool)| {
                let mut core = tool.contact_params();
                if let Some(p) = self.proxies.iter().find(|p| p.tool == index) {
                    let shift = p.x - core.a;
                    (core.a, core.b) = (core.a + shift, core.b + shift);
                }
                ToolCore { tool: index, core }
            })
            .collect();
        if cores.is_empty() {
            return Vec::new();
        }
        let x = self.positions_f64();
        self.surface.refit(&x);
        let radius = cores.iter().map(|c| c.core.radius).fold(f64::INFINITY, f64::min);
        let margin = if speculative { 0.5 * radius.min(self.surface.spacing()) } else { 0.0 };
        self.surface.detect(&cores, &x, margin)
    }

    /// Whether tool `index` went through the surface: a surface-contact tool that touches
    /// nothing while its tip lies inside the body (a teleport, or a step too long for its
    /// samples to meet a face). Nothing holds it there, and the report says so. Call after
    /// `detect_contacts` refitted the surface to the current positions.
    pub(super) fn passed_through(&self, index: usize) -> bool {
        let tool = &self.tools[index];
        if tool.contact != ContactModel::Surface || self.contacts.iter().any(|c| c.tool == index) {
            return false;
        }
        let tip = self.proxies.iter().find(|p| p.tool == index).map_or_else(|| tool.tip(), |p| p.x);
        self.surface.encloses(&tip, |i| self.world(i as usize).map(T::to_f64))
    }

    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn external_forces(&self) -> &[Vector3<T>] {
        &self.external
    }

    /// The simulated tools' rows and the surface contacts' terms (few: sequential, so the
    /// sums keep their order). A contact of depth φ has energy ½kφ² and gradient g_r on its
    /// rows (minus a node's share of the push, the push on a simulated tool), hence
    /// b_r += -h k (φ + h φ̇) g_r with φ̇ = Σ g·v, and A += h² k g gᵀ.
    pub(super) fn assemble_tools(&mut self) {
        let n = self.u.len();
        let h = self.params.dt;
        for (k, proxy) in self.proxies.iter().enumerate() {
            let tool = &self.tools[proxy.tool];
            let Some(coupling) = tool.coupling else { continue };
            let (force, stiffness, damping, _) = coupling_force(tool, proxy);
            let diag = Matrix3::identity() * (coupling.mass + h * damping + h * h * stiffness);
            self.proxy_diag[k] = diag.map(T::of);
            self.rhs[n + k] = ((force - proxy.v * (h * stiffness)) * h).map(T::of);
            self.precond[n + k] = diag.try_inverse().unwrap_or_else(Matrix3::zeros).map(T::of);
        }
        self.contact_rows.clear();
        self.rows_before_contacts.clear();
        self.add_contacts();
    }

    /// Adds the contacts' terms to the assembled rows, keeping each touched row as it was.
    pub(super) fn add_contacts(&mut self) {
        let n = self.u.len();
        let h = self.params.dt;
        let mut blocks: Vec<(usize, Matrix3<f64>)> = Vec::new();
        for c in &self.active_contacts {
            let mut rows = [usize::MAX; CONTACT_NODES + 1];
            let mut gradients = [Vector3::zeros(); CONTACT_NODES + 1];
            let mut normal_speed = 0.0;
            for (k, (&node, share)) in c.nodes.iter().zip(&c.shares).enumerate() {
                if node != u32::MAX && !self.fixed[node as usize] {
                    rows[k] = node as usize;
                    gradients[k] = -share;
                    normal_speed -= share.dot(&self.v[node as usize].map(T::to_f64));
                }
            }
            if let Some(k) = self.proxies.iter().position(|p| p.tool == c.tool) {
                rows[CONTACT_NODES] = n + k;
                gradients[CONTACT_NODES] = c.push;
                normal_speed += c.push.dot(&self.proxies[k].v);
            }
            let g = h * c.stiffness * (c.depth + h * normal_speed);
            for (&row, gradient) in rows.iter().zip(&gradients).filter(|(row, _)| **row != usize::MAX) {
                if !self.rows_before_contacts.iter().any(|(r, _, _)| *r == row) {
                    self.rows_before_contacts.push((row, self.rhs[row], self.precond[row]));
                }
                self.rhs[row] -= (gradient * g).map(T::of);
                blocks.push((row, gradient * gradient.transpose() * (h * h * c.stiffness)));
            }
            self.contact_rows.push(ContactRows {
                rows,
                gradients: gradients.map(|g| g.map(T::of)),
                h2k: T::of(h * h * c.stiffness),
            });
        }
        // Block Jacobi sees each touched row's diagonal block with its contact part.
        blocks.sort_by_key(|(row, _)| *row);
        for group in blocks.chunk_by(|a, b| a.0 == b.0) {
            let row = group[0].0;
            let base = if row < n { self.diag[row] } else { self.proxy_diag[row - n] };
            let sum = group.iter().fold(base.map(T::to_f64), |s, (_, b)| s + b);
            self.precond[row] = sum.try_inverse().unwrap_or_else(Matrix3::zeros).map(T::of);
        }
    }

    /// Backward Euler evaluates the contact at the step's end, linearised: a contact whose
    /// end penetration φ + h φ̇ comes out ≤ 0 would pull the surface, so it leaves the active
    /// set and the step is solved again from the rows as they were (a few rounds at most).
    pub(super) fn release_separating_contacts(&mut self) -> bool {
        let n = self.u.len();
        let h = T::of(self.params.dt);
        let keep: Vec<bool> = (self.active_contacts.iter().zip(&self.contact_rows))
            .map(|(c, rows)| {
                let mut rate = T::zero();
                for (&row, gradient) in rows.rows.iter().zip(&rows.gradients).filter(|(row, _)| **row != usize::MAX) {
                    let v = if row < n { self.v[row] } else { self.proxies[row - n].v.map(T::of) };
                    rate += gradient.dot(&(v + self.dv[row]));
                }
                T::of(c.depth) + h * rate > T::zero()
            })
            .collect();
        let mut keep = keep;
        for (k, c) in self.active_contacts.iter().enumerate().skip(1) {
            if c.joins_previous {
                keep[k] = keep[k - 1];
            }
        }
        if keep.iter().all(|k| *k) {
            return false;
        }
        for (row, rhs, precond) in self.rows_before_contacts.drain(..) {
            self.rhs[row] = rhs;
            self.precond[row] = precond;
        }
        let mut k = keep.iter();
        self.active_contacts.retain(|_| k.next().copied().unwrap_or(false));
        self.contact_rows.clear();
        self.add_contacts();
        true
    }

    /// out += the surface contacts' part of A p (rank one per contact).
    pub(super) fn contact_product(&self, p: &[Vector3<T>], out: &mut [Vector3<T>]) {
        for c in &self.contact_rows {
            let touched = || c.rows.iter().zip(&c.gradients).filter(|(row, _)| **row != usize::MAX);
            let y = touched().fold(T::zero(), |y, (&row, gradient)| y + gradient.dot(&p[row]));
            let s = c.h2k * y;
            for (&row, gradient) in touched() {
                out[row] += gradient * s;
            }
        }
    }
}
