//! The explicit schemes (forward Euler, Verlet, velocity Verlet): the forces of the
//! springs, gravity, the tools and the surface contacts, then one update per node.

use super::*;

impl<T: Real> Simulation<T> {
    /// Forces on every node at the current (x, v); `v_eval` overrides the velocities.
    pub(super) fn forces(&self, tools: &[ContactTool<T>], v_eval: &[Vector3<T>]) -> Vec<Vector3<T>> {
        let g = Vector3::from(self.params.gravity).map(T::of);
        let h = T::of(self.params.dt);
        let spring_forces: Vec<Vector3<T>> = (0..self.springs.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|e| {
                let [a, b] = self.springs[e];
                let (a, b) = (a as usize, b as usize);
                let d = self.rest_edge[e] + self.u[b] - self.u[a];
                kernels::spring_force(
                    &d,
                    &v_eval[a],
                    &v_eval[b],
                    self.rest_length[e],
                    self.stiffness[e],
                    self.damping[e],
                )
            })
            .collect();
        let terms: Vec<SpringTerms<T>> = spring_forces
            .into_iter()
            .map(|force| SpringTerms { force, kv: Vector3::zeros(), block: Matrix3::zeros() })
            .collect();
        let mut forces = (0..self.u.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|i| {
                let adj = &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize];
                kernels::node_terms(
                    i,
                    adj,
                    &self.springs,
                    &terms,
                    self.mass[i],
                    self.fixed[i],
                    &self.world(i),
                    &v_eval[i],
                    &self.external[i],
                    &g,
                    tools,
                    h,
                )
                .force
            })
            .collect::<Vec<_>>();
        // Explicit updates hold fixed nodes whatever their force.
        add_contact_forces(&self.active_contacts, &mut forces);
        forces
    }

    pub(super) fn explicit_euler(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        let f = self.forces(tools, &self.v);
        let (mass, fixed) = (&self.mass, &self.fixed);
        self.u.par_iter_mut().zip(self.v.par_iter_mut()).enumerate().for_each(|(i, (x, v))| {
            if fixed[i] {
                *v = Vector3::zeros();
                return;
            }
            *x += *v * h;
            *v += f[i] * (h / mass[i]);
        });
    }

    /// Position (Störmer) Verlet. The velocity (for damping and reports) is the half-step
    /// difference plus half a step of acceleration: second order, like the positions.
    pub(super) fn verlet(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        if !self.history_valid {
            self.history = self.u.iter().zip(&self.v).map(|(u, v)| u - v * h).collect();
            self.history_valid = true;
        }
        let f = self.forces(tools, &self.v);
        let (mass, fixed) = (&self.mass, &self.fixed);
        let two = T::of(2.0);
        (self.u.par_iter_mut(), self.v.par_iter_mut(), self.history.par_iter_mut())
            .into_par_iter()
            .enumerate()
            .for_each(|(i, (x, v, prev))| {
                if fixed[i] {
                    *v = Vector3::zeros();
                    *prev = *x;
                    return;
                }
                let accel = f[i] / mass[i];
                let next = *x * two - *prev + accel * (h * h);
                *v = (next - *x) / h + accel * (h * T::of(0.5));
                *prev = *x;
                *x = next;
            });
    }

    /// Velocity Verlet; the damping force at the new positions uses the predicted velocity.
    pub(super) fn velocity_verlet(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        let half = T::of(0.5);
        if !self.history_valid {
            let f = self.forces(tools, &self.v);
            self.history = f.iter().zip(&self.mass).map(|(f, m)| f / *m).collect();
            self.history_valid = true;
        }
        let fixed = &self.fixed;
        let accel = &self.history;
        self.u.par_iter_mut().zip(self.v.par_iter()).enumerate().for_each(|(i, (x, v))| {
            if !fixed[i] {
                *x += v * h + accel[i] * (half * h * h);
            }
        });
        let predicted: Vec<Vector3<T>> = self.v.iter().zip(accel).map(|(v, a)| v + a * h).collect();
        let f = self.forces(tools, &predicted);
        let mass = &self.mass;
        self.v.par_iter_mut().zip(self.history.par_iter_mut()).enumerate().for_each(|(i, (v, a))| {
            let a_new = f[i] / mass[i];
            *v = if fixed[i] { Vector3::zeros() } else { *v + (*a + a_new) * (half * h) };
            *a = a_new;
        });
    }
}
