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
            return Err(SolverError::Diverged { step: failed.0, time: failed.1, reason });
        }
        Ok(report)
    }

    pub(super) fn divergence(&self, report: &StepReport) -> Option<String> {
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
}
