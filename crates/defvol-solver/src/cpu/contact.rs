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
            if let Some(friction) = &tool.friction {
                friction.validate(index)?;
                self.surface_and_implicit(index, "friction", friction.static_coefficient)?;
            }
            if let Some(rotational) = &tool.rotational_coupling {
                rotational.validate(index)?;
                if tool.coupling.is_none() {
                    return Err(SolverError::BadParameter {
                        name: format!("tools[{index}].rotational_coupling"),
                        value: rotational.stiffness,
                        why: "turns a coupled tool: give the tool a coupling too".into(),
                    });
                }
            }
            if let Some(coupling) = &tool.coupling {
                coupling.validate(index)?;
                self.surface_and_implicit(index, "coupling", coupling.stiffness)?;
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

    /// An error unless tool `index` is on surface contact and the integrator implicit Euler:
    /// what its `field` (coupling, friction: rows of the implicit system) needs.
    fn surface_and_implicit(&self, index: usize, field: &str, value: f64) -> Result<(), SolverError> {
        let why = if self.tools[index].contact != ContactModel::Surface {
            "needs surface contact"
        } else if self.params.integrator != Integrator::ImplicitEuler {
            "needs the implicit_euler integrator (its rows are in the implicit system)"
        } else {
            return Ok(());
        };
        Err(SolverError::BadParameter { name: format!("tools[{index}].{field}"), value, why: format!("{field} {why}") })
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
            let mut turning_row = self.u.len() + coupled.len();
            self.proxies = coupled
                .iter()
                .map(|&tool| {
                    let pose = self.tools[tool].world_from_tool;
                    let tip = pose.translation.vector;
                    let turning = self.tools[tool].rotational_coupling.map(|_| {
                        turning_row += 1;
                        Turning {
                            orientation: pose.rotation,
                            omega: Vector3::zeros(),
                            device: pose.rotation,
                            device_omega: Vector3::zeros(),
                            row: turning_row - 1,
                        }
                    });
                    Proxy { tool, x: tip, v: Vector3::zeros(), device: tip, device_velocity: Vector3::zeros(), turning }
                })
                .collect();
            let rows = turning_row;
            self.rhs.resize(rows, Vector3::zeros());
            self.precond.resize(rows, Matrix3::zeros());
            for w in [&mut self.dv, &mut self.dv_previous, &mut self.r, &mut self.z, &mut self.p, &mut self.q] {
                w.resize(rows, Vector3::zeros());
            }
            self.proxy_diag = vec![Matrix3::zeros(); rows - self.u.len()];
        }
        let dt = self.params.dt;
        for p in &mut self.proxies {
            let pose = self.tools[p.tool].world_from_tool;
            p.device_velocity = (pose.translation.vector - p.device) / dt;
            p.device = pose.translation.vector;
            if let Some(turning) = &mut p.turning {
                turning.device_omega = (pose.rotation * turning.device.inverse()).scaled_axis() / dt;
                turning.device = pose.rotation;
            }
        }
        self.tool_tips.resize(self.tools.len(), None);
        self.tool_velocities.resize(self.tools.len(), Vector3::zeros());
        for (k, tool) in self.tools.iter().enumerate() {
            let tip = tool.tip();
            self.tool_velocities[k] = self.tool_tips[k].map_or_else(Vector3::zeros, |last| (tip - last) / dt);
            self.tool_tips[k] = Some(tip);
        }
    }

    /// The surface contacts of the surface-contact tools at the current positions; with
    /// `speculative`, those about to begin too (within half the radius or spacing).
    /// A simulated tool's margin also covers the farthest it can travel in the step (its
    /// speed, and the coupling's largest pull on its mass), so one pulled fast at the
    /// surface meets it within the step instead of passing it between two steps.
    pub(super) fn detect_contacts(&mut self, speculative: bool) -> Vec<SurfaceContact> {
        let h = self.params.dt;
        let cores: Vec<(ToolCore, f64)> = (self.tools.iter().enumerate())
            .filter(|(_, tool)| tool.contact == ContactModel::Surface && tool.contact_stiffness > 0.0)
            .map(|(index, tool)| {
                let mut core = tool.contact_params();
                let mut travel = 0.0;
                if let (Some(p), Some(coupling)) = (self.proxies.iter().find(|p| p.tool == index), tool.coupling) {
                    // The simulated tool's core: at its tip, turned as it is.
                    let turn = p.turning.as_ref().map_or_else(nalgebra::UnitQuaternion::identity, |t| {
                        t.orientation * tool.world_from_tool.rotation.inverse()
                    });
                    (core.a, core.b) = (p.x, p.x + turn * (core.b - core.a));
                    travel = p.v.norm() * h + coupling.max_force / coupling.mass * h * h;
                }
                (ToolCore { tool: index, core }, travel)
            })
            .collect();
        if self.touches_surface() {
            self.surface.keep_fitted(&Displaced { rest: &self.rest, u: &self.u });
        }
        if cores.is_empty() {
            return Vec::new();
        }
        let x = Displaced { rest: &self.rest, u: &self.u };
        let spacing = self.surface.spacing();
        (cores.iter())
            .flat_map(|(core, travel)| {
                let margin = if speculative { (0.5 * core.core.radius.min(spacing)).max(*travel) } else { 0.0 };
                self.surface.detect(std::slice::from_ref(core), &x, margin)
            })
            .collect()
    }

    /// Whether a tool meets the boundary surface (surface contact), so that its hierarchy
    /// is queried and kept fitted.
    /// Whether a step needs nothing the host computes from the state before it: no tool
    /// touches the surface (its contacts are found on the host) nor has a commanded force
    /// (spread over the nodes near its tip, weighted by where they are).
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn steps_without_the_host(&self) -> bool {
        !self.touches_surface() && self.tools.iter().all(|tool| tool.applied_force == Vector3::zeros())
    }

    pub(super) fn touches_surface(&self) -> bool {
        self.tools.iter().any(|tool| tool.contact == ContactModel::Surface)
    }

    /// Whether tool `index` went through the surface: a surface-contact tool that touches
    /// nothing while its tip lies inside the body (a teleport, or a step too long for its
    /// samples to meet a face). Nothing holds it there, and the report says so.
    pub(super) fn passed_through(&self, index: usize) -> bool {
        let tool = &self.tools[index];
        if tool.contact != ContactModel::Surface || self.contacts.iter().any(|c| c.tool == index) {
            return false;
        }
        let tip = self.proxies.iter().find(|p| p.tool == index).map_or_else(|| tool.tip(), |p| p.x);
        self.surface.encloses(&tip, &Displaced { rest: &self.rest, u: &self.u })
    }

    /// The forces a GPU step takes as given: the commanded ones spread on the nodes, and
    /// for the explicit schemes the surface contacts' (the implicit one assembles those).
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn external_forces(&self) -> Vec<Vector3<T>> {
        let mut forces = self.external.clone();
        if self.params.integrator != Integrator::ImplicitEuler {
            add_contact_forces(&self.active_contacts, &mut forces);
        }
        forces
    }

    /// The surface contacts of the step being solved.
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn active_contacts(&self) -> &[SurfaceContact] {
        &self.active_contacts
    }

    /// How many simulated tools the implicit system carries (rows after the nodes').
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn proxy_count(&self) -> usize {
        self.proxies.len()
    }

    /// The simulated tools' rows and the surface contacts' terms (few: sequential, so the
    /// sums keep their order).
    pub(super) fn assemble_tools(&mut self) {
        for k in 0..self.proxies.len() {
            for (row, diag, rhs) in self.proxy_row(k).into_iter().chain(self.turning_row(k)) {
                self.rhs[row] = rhs.map(T::of);
                self.precond[row] = diag.try_inverse().unwrap_or_else(Matrix3::zeros).map(T::of);
            }
        }
        self.contact_rows.clear();
        self.rows_before_contacts.clear();
        self.add_contacts();
    }

    /// Simulated tool k's row, (M + hD + h²K) Δv = h (f - h K v): its diagonal block (kept
    /// for the local model) and right-hand side (both backends assemble it so).
    pub(crate) fn proxy_row(&mut self, k: usize) -> Option<(usize, Matrix3<f64>, Vector3<f64>)> {
        let proxy = self.proxies.get(k)?;
        let tool = &self.tools[proxy.tool];
        let coupling = tool.coupling?;
        let h = self.params.dt;
        let (force, stiffness, damping, _) = coupling_force(tool, proxy);
        let diag = Matrix3::identity() * (coupling.mass + h * damping + h * h * stiffness);
        let rhs = (force - proxy.v * (h * stiffness)) * h;
        self.proxy_diag[k] = diag.map(T::of);
        Some((self.u.len() + k, diag, rhs))
    }

    /// The row simulated tool k turns on (a rotational coupling), (I + hC + h²K) Δω =
    /// h (τ - h K ω), as its translational row.
    pub(crate) fn turning_row(&mut self, k: usize) -> Option<(usize, Matrix3<f64>, Vector3<f64>)> {
        let proxy = self.proxies.get(k)?;
        let (tool, turning) = (&self.tools[proxy.tool], proxy.turning.as_ref()?);
        let rotational = tool.rotational_coupling?;
        let h = self.params.dt;
        let (torque, stiffness, damping, _) = twisting(tool, turning);
        let diag = Matrix3::identity() * (rotational.inertia + h * damping + h * h * stiffness);
        let rhs = (torque - turning.omega * (h * stiffness)) * h;
        self.proxy_diag[turning.row - self.u.len()] = diag.map(T::of);
        Some((turning.row, diag, rhs))
    }

    /// Whether row `row` of the system is a fixed node's (the simulated tools' are free).
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn fixed_row(&self, row: usize) -> bool {
        self.fixed.get(row).copied().unwrap_or(false)
    }

    /// A surface contact's terms in the implicit system (both backends assemble them so).
    /// A contact of depth φ has energy ½kφ² and gradient g_r on its rows (minus a node's
    /// share of the push, the push on a simulated tool), hence b_r -= h k (φ + h φ̇) g_r
    /// with φ̇ = Σ g·v, and A += h² k g gᵀ.
    fn contact_terms(&self, c: &SurfaceContact) -> ContactTerms {
        let n = self.u.len();
        let h = self.params.dt;
        let mut rows = [usize::MAX; TERM_ROWS];
        let mut gradients = [Vector3::zeros(); TERM_ROWS];
        let mut normal_speed = 0.0;
        for (k, (&node, share)) in c.nodes.iter().zip(&c.shares).enumerate() {
            if node != u32::MAX && !self.fixed[node as usize] {
                rows[k] = node as usize;
                gradients[k] = -share;
                normal_speed -= share.dot(&self.v[node as usize].map(T::to_f64));
            }
        }
        if let Some(k) = self.proxies.iter().position(|p| p.tool == c.tool) {
            let proxy = &self.proxies[k];
            rows[CONTACT_NODES] = n + k;
            gradients[CONTACT_NODES] = c.push;
            normal_speed += c.push.dot(&proxy.v);
            if let Some(turning) = &proxy.turning {
                // Turning about its tip moves the contact by ω × (at - tip): exact, as the
                // contact point lies from the core's sample along the push.
                let lever = (c.at - proxy.x).cross(&c.push);
                (rows[CONTACT_NODES + 1], gradients[CONTACT_NODES + 1]) = (turning.row, lever);
                normal_speed += lever.dot(&turning.omega);
            }
        }
        ContactTerms {
            rows,
            gradients,
            h2k: h * h * c.stiffness,
            rhs_scale: h * c.stiffness * (c.depth + h * normal_speed),
            normal_speed,
        }
    }

    /// The terms of the system beyond the springs for both backends: the active contacts'
    /// (in their order), then their friction's (kept in `frictions` for its forces).
    pub(crate) fn system_terms(&mut self) -> Vec<ContactTerms> {
        let contacts = self.active_contacts.clone();
        self.frictions = contacts.iter().flat_map(|c| self.friction_terms(c)).collect();
        let mut terms: Vec<ContactTerms> = contacts.iter().map(|c| self.contact_terms(c)).collect();
        terms.extend(self.frictions.iter().map(|f| f.terms));
        terms
    }

    /// A pressing contact's friction: two rank-one dampers along its tangents on the
    /// sliding velocity w = v_tool - Σ w_i v_i (w_i its nodes' barycentric weights), their
    /// coefficient from the tool's `Friction` at the contact's force and w at the step's
    /// start. The force on a row is -c g (t·w), g = ∂(t·w)/∂v of the row.
    fn friction_terms(&self, c: &SurfaceContact) -> Vec<FrictionTerm> {
        let Some(friction) = self.tools[c.tool].friction else { return Vec::new() };
        if c.joins_previous || c.depth <= 0.0 {
            return Vec::new();
        }
        let mut rows = [usize::MAX; TERM_ROWS];
        let mut weights = [0.0; TERM_ROWS];
        let mut sliding = Vector3::zeros();
        for (k, (&node, share)) in c.nodes.iter().zip(&c.shares).enumerate().filter(|(_, (n, _))| **n != u32::MAX) {
            let w = share.dot(&c.push);
            sliding -= self.v[node as usize].map(T::to_f64) * w;
            if !self.fixed[node as usize] {
                (rows[k], weights[k]) = (node as usize, -w);
            }
        }
        let mut turning = None;
        match self.proxies.iter().position(|p| p.tool == c.tool) {
            Some(k) => {
                let proxy = &self.proxies[k];
                (rows[CONTACT_NODES], weights[CONTACT_NODES]) = (self.u.len() + k, 1.0);
                sliding += proxy.v;
                if let Some(t) = &proxy.turning {
                    let lever = c.at - proxy.x;
                    rows[CONTACT_NODES + 1] = t.row;
                    sliding += t.omega.cross(&lever);
                    turning = Some(lever);
                }
            }
            None => sliding += self.tool_velocities.get(c.tool).copied().unwrap_or_else(Vector3::zeros),
        }
        let tangential = sliding - c.push * c.push.dot(&sliding);
        let damping = friction.damping(c.stiffness * c.depth, tangential.norm());
        let h = self.params.dt;
        tangents(&c.push)
            .into_iter()
            .map(|tangent| {
                let speed = tangent.dot(&sliding);
                let mut gradients = weights.map(|w| tangent * w);
                if let Some(lever) = turning {
                    gradients[CONTACT_NODES + 1] = lever.cross(&tangent);
                }
                let terms = ContactTerms {
                    rows,
                    gradients,
                    h2k: h * damping,
                    rhs_scale: h * damping * speed,
                    normal_speed: speed,
                };
                FrictionTerm { tool: c.tool, at: c.at, tangent, damping, terms }
            })
            .collect()
    }

    /// The friction forces at the step's end, from each friction term's speed there
    /// (t·w + Σ g·Δv, in `frictions`' order).
    pub(crate) fn record_friction(&mut self, end_speeds: &[f64]) {
        let n = self.u.len();
        self.friction_forces = (self.frictions.iter().zip(end_speeds))
            .map(|(f, speed)| {
                let along = -f.damping * speed;
                let on_nodes = f.terms.touched().filter(|(row, _)| *row < n).map(|(row, g)| (row, g * along)).collect();
                FrictionForce { tool: f.tool, at: f.at, on_tool: f.tangent * along, on_nodes }
            })
            .collect();
    }

    /// Adds the contacts' terms to the assembled rows, keeping each touched row as it was.
    pub(super) fn add_contacts(&mut self) {
        let n = self.u.len();
        let mut blocks: Vec<(usize, Matrix3<f64>)> = Vec::new();
        for terms in self.system_terms() {
            for (row, gradient) in terms.touched() {
                if !self.rows_before_contacts.iter().any(|(r, _, _)| *r == row) {
                    self.rows_before_contacts.push((row, self.rhs[row], self.precond[row]));
                }
                self.rhs[row] -= (gradient * terms.rhs_scale).map(T::of);
                blocks.push((row, gradient * gradient.transpose() * terms.h2k));
            }
            self.contact_rows.push(ContactRows {
                rows: terms.rows,
                gradients: terms.gradients.map(|g| g.map(T::of)),
                h2k: T::of(terms.h2k),
                normal_speed: terms.normal_speed,
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
        let end_rates = self.end_rates();
        if !self.release_contacts(&end_rates[..self.active_contacts.len()]) {
            return false;
        }
        for (row, rhs, precond) in self.rows_before_contacts.drain(..) {
            self.rhs[row] = rhs;
            self.precond[row] = precond;
        }
        self.contact_rows.clear();
        self.add_contacts();
        true
    }

    /// Drops the active contacts that separate at the step's end, given each one's rate
    /// φ̇ = Σ g·(v + Δv) there (a row that joins the contact before it goes with it);
    /// whether any went.
    pub(crate) fn release_contacts(&mut self, end_rates: &[f64]) -> bool {
        let h = self.params.dt;
        let mut keep: Vec<bool> =
            self.active_contacts.iter().zip(end_rates).map(|(c, rate)| c.depth + h * rate > 0.0).collect();
        for (k, c) in self.active_contacts.iter().enumerate().skip(1) {
            if c.joins_previous {
                keep[k] = keep[k - 1];
            }
        }
        if keep.iter().all(|k| *k) {
            return false;
        }
        let mut k = keep.iter();
        self.active_contacts.retain(|_| k.next().copied().unwrap_or(false));
        true
    }

    /// Each contact row's rate at the step's end, Σ g·(v + Δv): the contacts' φ̇, then the
    /// friction terms' sliding speeds.
    pub(super) fn end_rates(&self) -> Vec<f64> {
        (self.contact_rows.iter())
            .map(|rows| {
                let moved = (rows.rows.iter().zip(&rows.gradients))
                    .filter(|(row, _)| **row != usize::MAX)
                    .fold(T::zero(), |rate, (&row, gradient)| rate + gradient.dot(&self.dv[row]));
                rows.normal_speed + moved.to_f64()
            })
            .collect()
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

impl<T: Real> Simulation<T> {
    /// Each coupled tool's local model for the force loop (`haptic.rs`), from the step just
    /// taken: the simulated tool, and the contact it presses condensed to one plane along
    /// the contact force. The plane's stiffness is what the step's own system says the tool
    /// feels along it: with A the system (the tool's row included), the tool's compliance
    /// s = nᵀ(A⁻¹)_tt n, so h²k = 1/s minus the tool's own row (one more solve). A tool
    /// touching nothing gets the nearest face it is about to touch, at the penalty's stiffness.
    pub fn local_models(&mut self) -> Vec<LocalModel> {
        let h = self.params.dt;
        (self.local_queries().into_iter())
            .map(|query| {
                let compliance = query.along().map_or(0.0, |b| self.compliance_along(b));
                query.finish(compliance, h)
            })
            .collect()
    }

    /// Each coupled tool's local model, short of the one number it may need of the step's
    /// system (bᵀA⁻¹b along the query's rows), which each backend solves for itself.
    pub(crate) fn local_queries(&mut self) -> Vec<LocalQuery> {
        let mut queries = Vec::with_capacity(self.proxies.len());
        for k in 0..self.proxies.len() {
            let proxy = self.proxies[k].clone();
            let Some(coupling) = self.tools[proxy.tool].coupling else { continue };
            let contact = self.local_contact(k);
            let turning = self.local_turning(&proxy);
            queries.push(LocalQuery::new(proxy.tool, coupling, proxy.x, proxy.v, proxy.device, contact, turning));
        }
        queries
    }

    /// A turning tool's part of its local model: its state and the contacts' torque on it
    /// about its tip at the end of the step (pushes and friction).
    fn local_turning(&self, proxy: &Proxy) -> Option<LocalTurning> {
        let (turning, coupling) = (proxy.turning.as_ref()?, self.tools[proxy.tool].rotational_coupling?);
        let mine = |tool: usize| tool == proxy.tool;
        let pushes = self.contacts.iter().filter(|c| mine(c.tool)).map(|c| (c.at - proxy.x).cross(&-c.force()));
        let rubs = self.friction_forces.iter().filter(|f| mine(f.tool)).map(|f| (f.at - proxy.x).cross(&f.on_tool));
        Some(LocalTurning {
            coupling,
            orientation: turning.orientation,
            omega: turning.omega,
            device: turning.device,
            contact_torque: pushes.chain(rubs).sum(),
        })
    }

    fn local_contact(&mut self, k: usize) -> Option<PendingContact> {
        let tool = self.proxies[k].tool;
        let force: Vector3<f64> =
            -self.contacts.iter().filter(|c| c.tool == tool).map(|c| c.force()).sum::<Vector3<f64>>();
        let Some(normal) = force.try_normalize(0.0) else {
            let ahead = self.detect_contacts(true);
            let c = ahead.iter().filter(|c| c.tool == tool).max_by(|a, b| a.depth.total_cmp(&b.depth))?;
            let c = *c;
            let surface_speed = self.surface_speed(std::slice::from_ref(&c));
            // The mesh's compliance there (h² gᵀA⁻¹g, g the contact's shares) in series.
            let along = c.node_forces().map(|(n, _)| n as usize).zip(c.shares.iter().copied()).collect();
            let rule = StiffnessRule::InSeries { depth: c.depth, penalty: c.stiffness };
            let friction = self.tools[tool].friction;
            let lever = (c.at - self.proxies[k].x).cross(&-c.push);
            return Some(PendingContact { normal: -c.push, lever, surface_speed, friction, along, rule });
        };
        let penalty: f64 = self.contacts.iter().filter(|c| c.tool == tool).map(|c| c.stiffness).fold(0.0, f64::max);
        let row = self.u.len() + k;
        // The final active set of the step: the tool's row joins every contact of its tool.
        let pressed = self.active_contacts.iter().any(|c| c.tool == tool);
        let mine: Vec<SurfaceContact> = self.contacts.iter().filter(|c| c.tool == tool).copied().collect();
        let surface_speed = self.surface_speed(&mine);
        // Where the push acts (its force-weighted point), for the lever that turns the tool.
        let at = mine.iter().map(|c| c.at * c.force().norm()).sum::<Vector3<f64>>() / force.norm();
        let lever = (at - self.proxies[k].x).cross(&normal);
        let (along, rule) = match pressed {
            true => {
                let own = normal.dot(&(self.proxy_diag[k].map(T::to_f64) * normal));
                (vec![(row, normal)], StiffnessRule::Condensed { force: force.norm(), own, penalty })
            }
            false => (Vec::new(), StiffnessRule::Penalty { force: force.norm(), penalty }),
        };
        Some(PendingContact { normal, lever, surface_speed, friction: self.tools[tool].friction, along, rule })
    }

    /// How fast the surface under `contacts` moves along their normal (out of the body):
    /// each contact's rate -Σ share·v over its nodes, weighted by its force.
    fn surface_speed(&self, contacts: &[SurfaceContact]) -> f64 {
        let (mut sum, mut weight) = (0.0, 0.0);
        for c in contacts.iter().filter(|c| !c.joins_previous) {
            let w = c.depth.abs().max(f64::MIN_POSITIVE);
            let rate: f64 = (c.nodes.iter().zip(&c.shares))
                .take_while(|(n, _)| **n != u32::MAX)
                .map(|(&n, share)| -share.dot(&self.v[n as usize].map(T::to_f64)))
                .sum();
            (sum, weight) = (sum + w * rate, weight + w);
        }
        if weight > 0.0 {
            sum / weight
        } else {
            0.0
        }
    }

    /// bᵀA⁻¹b for the assembled system A and b given on a few rows: one solve, the step's
    /// Δv and right-hand side kept.
    fn compliance_along(&mut self, b: &[(usize, Vector3<f64>)]) -> f64 {
        let (dv, rhs) = (self.dv.clone(), self.rhs.clone());
        self.rhs.iter_mut().for_each(|r| *r = Vector3::zeros());
        for (row, v) in b.iter().filter(|(row, _)| *row >= self.u.len() || !self.fixed[*row]) {
            self.rhs[*row] += v.map(T::of);
        }
        self.dv.iter_mut().for_each(|v| *v = Vector3::zeros());
        self.solve();
        let compliance = b.iter().map(|(row, v)| v.dot(&self.dv[*row].map(T::to_f64))).sum();
        (self.dv, self.rhs) = (dv, rhs);
        compliance
    }
}

/// Two unit tangents of the plane normal to `n`, orthogonal to each other.
fn tangents(n: &Vector3<f64>) -> [Vector3<f64>; 2] {
    let away = if n.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let t1 = n.cross(&away).normalize();
    [t1, n.cross(&t1)]
}
