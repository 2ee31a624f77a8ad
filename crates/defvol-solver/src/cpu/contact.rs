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
    /// sums keep their order). A contact of depth φ along n has energy ½kφ², ∇φ = Σ_r c_r n
    /// over its rows (c = -w on the face's nodes, +1 on a simulated tool), hence
    /// b_r += -c_r h k (φ + h φ̇) n with φ̇ = n·Σ c v, and A += h² k (c cᵀ) ⊗ n nᵀ.
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
            let proxy = self.proxies.iter().position(|p| p.tool == c.tool);
            let mut rows = [usize::MAX; 4];
            let mut coefficients = [0.0; 4];
            for k in 0..3 {
                if c.weights[k] > 0.0 && !self.fixed[c.nodes[k] as usize] {
                    rows[k] = c.nodes[k] as usize;
                    coefficients[k] = -c.weights[k];
                }
            }
            if let Some(k) = proxy {
                rows[3] = n + k;
                coefficients[3] = 1.0;
            }
            let mut normal_speed = 0.0;
            for k in 0..3 {
                normal_speed -= c.weights[k] * c.push.dot(&self.v[c.nodes[k] as usize].map(T::to_f64));
            }
            if let Some(k) = proxy {
                normal_speed += c.push.dot(&self.proxies[k].v);
            }
            let g = h * c.stiffness * (c.depth + h * normal_speed);
            let nn = c.push * c.push.transpose() * (h * h * c.stiffness);
            for r in 0..4 {
                if rows[r] != usize::MAX {
                    if !self.rows_before_contacts.iter().any(|(row, _, _)| *row == rows[r]) {
                        self.rows_before_contacts.push((rows[r], self.rhs[rows[r]], self.precond[rows[r]]));
                    }
                    self.rhs[rows[r]] -= (c.push * (coefficients[r] * g)).map(T::of);
                    blocks.push((rows[r], nn * (coefficients[r] * coefficients[r])));
                }
            }
            self.contact_rows.push(ContactRows {
                rows,
                coefficients: coefficients.map(T::of),
                push: c.push.map(T::of),
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
                for r in 0..4 {
                    let row = rows.rows[r];
                    if row == usize::MAX {
                        continue;
                    }
                    let v = if row < n { self.v[row] } else { self.proxies[row - n].v.map(T::of) };
                    rate += rows.coefficients[r] * rows.push.dot(&(v + self.dv[row]));
                }
                T::of(c.depth) + h * rate > T::zero()
            })
            .collect();
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
            let mut y = T::zero();
            for r in 0..4 {
                if c.rows[r] != usize::MAX {
                    y += c.coefficients[r] * c.push.dot(&p[c.rows[r]]);
                }
            }
            let s = c.h2k * y;
            for r in 0..4 {
                if c.rows[r] != usize::MAX {
                    out[c.rows[r]] += c.push * (c.coefficients[r] * s);
                }
            }
        }
    }
}
