//! A step that diverges is undone: the state is saved before it, checked after it, and
//! restored with the reason when it went wrong.

use super::*;

impl<T: Real> Simulation<T> {
    pub(super) fn snapshot(&self) -> Snapshot<T> {
        Snapshot {
            u: self.u.clone(),
            v: self.v.clone(),
            history: self.history.clone(),
            history_valid: self.history_valid,
            proxies: self.proxies.clone(),
        }
    }

    /// Takes a state computed elsewhere (the GPU) as the result of `steps` steps, with the
    /// same reporting and divergence check as a CPU step; `proxy_dv` moves the simulated
    /// tools. A batch that diverged is undone whole.
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn accept_steps(
        &mut self,
        u: Vec<Vector3<T>>,
        v: Vec<Vector3<T>>,
        proxy_dv: &[Vector3<f64>],
        cg: CgStats,
        steps: u32,
    ) -> Result<StepReport, SolverError> {
        let saved = self.snapshot();
        self.u = u;
        self.v = v;
        self.advance_proxies(proxy_dv);
        self.last_cg = cg;
        self.finish_steps(saved, steps)
    }

    /// Counts `steps` steps taken from `saved`, checks and reports the state they reached.
    pub(super) fn finish_steps(&mut self, saved: Snapshot<T>, steps: u32) -> Result<StepReport, SolverError> {
        let (step_before, time_before) = (self.step, self.time);
        for _ in 0..steps {
            // As single steps count time, to the bit.
            self.step += 1;
            self.time += self.params.dt;
        }
        // The farthest any node moved, which keeps the contact hierarchy's boxes
        // conservative; measured only where a tool touches the surface.
        let moved = match self.touches_surface() {
            true => (self.u.par_iter().zip(saved.u.par_iter()))
                .map(|(now, before)| (now.map(T::to_f64) - before.map(T::to_f64)).norm())
                .reduce(|| 0.0, f64::max),
            false => f64::INFINITY,
        };
        self.surface.moved(moved);
        self.contacts = self.detect_contacts(false).into_iter().filter(|c| !c.joins_previous).collect();
        let report = self.report();
        if let Some(reason) = self.divergence(&report) {
            let failed = (self.step, self.time);
            self.u = saved.u;
            self.v = saved.v;
            self.history = saved.history;
            self.history_valid = saved.history_valid;
            self.proxies = saved.proxies;
            self.surface.moved(moved);
            (self.step, self.time) = (step_before, time_before);
            if self.fell_freely(&report) {
                return Err(SolverError::FellFreely {
                    step: failed.0,
                    time: failed.1,
                    distance: report.max_displacement,
                });
            }
            return Err(SolverError::Diverged { step: failed.0, time: failed.1, reason });
        }
        Ok(report)
    }

    /// Whether a state that moved too far is a mesh nothing holds, falling: no node fixed,
    /// every value finite.
    fn fell_freely(&self, report: &StepReport) -> bool {
        !self.fixed.contains(&true)
            && report.max_displacement > self.divergence_distance
            && report.max_displacement.is_finite()
            && report.kinetic_energy.is_finite()
    }

    /// Why the state reached is not physical, with where it points ([`Self::diagnosis`]).
    pub(super) fn divergence(&self, report: &StepReport) -> Option<String> {
        let reason = self.divergence_reason(report)?;
        Some(format!("{reason}; {}", self.diagnosis()))
    }

    fn divergence_reason(&self, report: &StepReport) -> Option<String> {
        if !self.u.iter().chain(self.v.iter()).all(|p| p.iter().all(|c| c.is_finite())) {
            return Some("non-finite positions or velocities".into());
        }
        let internal = report.kinetic_energy + self.spring_energy();
        if internal > self.divergence_energy {
            return Some(format!(
                "energy grew to {internal:.3e} J, beyond {:.3e} J (every spring stretched by its own length)",
                self.divergence_energy
            ));
        }
        if report.max_displacement > self.divergence_distance {
            return Some(format!("a node moved {:.3e} m, twice the mesh's size", report.max_displacement));
        }
        None
    }

    /// Where a diverged state points: the step's CG outcome, the spring stretched or crushed
    /// most, the node that moved farthest, and each tool's contacts and simulated tool.
    fn diagnosis(&self) -> String {
        let mut parts = Vec::new();
        if self.params.integrator == Integrator::ImplicitEuler {
            let cg = self.last_cg;
            let unconverged = match cg.relative_residual <= self.params.cg_tolerance {
                true => "",
                false => " (did not converge)",
            };
            parts
                .push(format!("CG {} its, relative residual {:.1e}{unconverged}", cg.iterations, cg.relative_residual));
        }
        let point = |p: Vector3<f64>| format!("({:.4}, {:.4}, {:.4}) m", p.x, p.y, p.z);
        let world = |i: usize| self.world(i).map(T::to_f64);
        let ends = |e: usize| self.springs[e].map(|n| n as usize);
        let ratio = |e: usize| {
            let [a, b] = ends(e);
            (world(b) - world(a)).norm() / self.rest_length[e].to_f64()
        };
        // Stretched or crushed alike: 2 and 0.5 of the rest length are as far from it.
        let strain = |e: usize| (ratio(e) - 1.0).abs().max(1.0 / ratio(e) - 1.0);
        let worst_spring = (0..self.springs.len()).max_by(|&a, &b| strain(a).total_cmp(&strain(b)));
        if let Some(e) = worst_spring {
            let ([a, b], ratio) = (ends(e), ratio(e));
            let at = point((world(a) + world(b)) * 0.5);
            parts.push(format!("worst spring {e} (nodes {a}-{b}) at {ratio:.3} of its rest length, at {at}"));
        }
        let moved = |i: usize| self.u[i].map(T::to_f64).norm();
        if let Some(i) = (0..self.u.len()).max_by(|&a, &b| moved(a).total_cmp(&moved(b))) {
            parts.push(format!("node {i} moved farthest, {:.3e} m, to {}", moved(i), point(world(i))));
        }
        for (index, t) in self.tools.iter().enumerate() {
            let contacts: Vec<_> = self.contacts.iter().filter(|c| c.tool == index).collect();
            let deepest = contacts.iter().map(|c| c.depth).fold(0.0, f64::max);
            let mut tool = match t.contact {
                ContactModel::Surface => {
                    format!("tool {index}: {} surface contacts, deepest {deepest:.2e} m", contacts.len())
                }
                ContactModel::Nodes => format!("tool {index}: contact on the nodes"),
            };
            if let Some(proxy) = self.proxies.iter().find(|p| p.tool == index) {
                tool += &format!(", simulated tool at {} (device at {})", point(proxy.x), point(proxy.device));
            }
            parts.push(tool);
        }
        parts.join("; ")
    }
}
