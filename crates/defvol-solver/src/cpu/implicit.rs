//! Implicit Euler: the system (M - h²K - hD) Δv = h f assembled per spring, solved by CG
//! with block Jacobi or the smoothed-aggregation AMG (`amg.rs`) as preconditioner.

use super::*;

impl<T: Real> Simulation<T> {
    /// Assembles A Δv = b at the current state (spring pass, then node gather).
    pub(crate) fn assemble(&mut self, tools: &[ContactTool<T>]) {
        let h = T::of(self.params.dt);
        let g = Vector3::from(self.params.gravity).map(T::of);
        let (u, v, rest_edge) = (&self.u, &self.v, &self.rest_edge);
        let (springs, rest, k, d) = (&self.springs, &self.rest_length, &self.stiffness, &self.damping);
        self.terms.par_iter_mut().with_min_len(CHUNK).enumerate().for_each(|(e, t)| {
            let [a, b] = springs[e];
            let (a, b) = (a as usize, b as usize);
            let edge = rest_edge[e] + u[b] - u[a];
            *t = kernels::spring_terms(&edge, &v[a], &v[b], rest[e], k[e], d[e], h);
        });
        let x: Vec<Vector3<T>> = (0..u.len()).map(|i| self.world(i)).collect();
        let terms = &self.terms;
        let (offsets, adjacency, mass, fixed, external) =
            (&self.offsets, &self.adjacency, &self.mass, &self.fixed, &self.external);
        (self.rhs.par_iter_mut(), self.diag.par_iter_mut(), self.precond.par_iter_mut())
            .into_par_iter()
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, (rhs, diag, precond))| {
                let adj = &adjacency[offsets[i] as usize..offsets[i + 1] as usize];
                let t = kernels::node_terms(
                    i,
                    adj,
                    springs,
                    terms,
                    mass[i],
                    fixed[i],
                    &x[i],
                    &v[i],
                    &external[i],
                    &g,
                    tools,
                    h,
                );
                *rhs = t.rhs;
                *diag = t.diag;
                *precond = t.precond;
            });
        self.assemble_tools();
    }

    pub(super) fn implicit_euler(&mut self, tools: &[ContactTool<T>]) {
        self.assemble(tools);
        // Start CG from Δv extrapolated linearly from the last two steps: the motion is
        // smooth in time, so this guess is closer than the last Δv alone.
        let last = self.dv.clone();
        if self.solves >= 2 {
            let two = T::of(2.0);
            self.dv
                .par_iter_mut()
                .zip(self.dv_previous.par_iter())
                .with_min_len(CHUNK)
                .for_each(|(dv, prev)| *dv = *dv * two - prev);
        }
        if self.multigrid && self.amg.as_ref().is_none_or(|a| a.stale) {
            self.build_amg();
        }
        self.last_cg = self.solve();
        if self.params.preconditioner == Preconditioner::Auto && self.last_cg.iterations > crate::AUTO_AMG_ABOVE {
            self.multigrid = true;
        }
        if let Some(state) = &mut self.amg {
            if state.iterations_at_build == 0 {
                state.iterations_at_build = self.last_cg.iterations.max(1);
            } else if crate::amg::is_stale(state.iterations_at_build, self.last_cg.iterations) {
                state.stale = true;
            }
        }
        for _ in 0..4 {
            if !self.release_separating_contacts() {
                break;
            }
            let first = self.last_cg.iterations;
            self.last_cg = self.solve();
            self.last_cg.iterations += first;
        }
        let end_rates = self.end_rates();
        self.record_friction(&end_rates[self.active_contacts.len()..]);
        self.dv_previous = last;
        self.solves += 1;
        let h = T::of(self.params.dt);
        let (dv, fixed) = (&self.dv, &self.fixed);
        self.u.par_iter_mut().zip(self.v.par_iter_mut()).enumerate().for_each(|(i, (x, v))| {
            if fixed[i] {
                *v = Vector3::zeros();
                return;
            }
            *v += dv[i];
            *x += *v * h;
        });
        let proxy_dv: Vec<Vector3<f64>> = self.dv[self.u.len()..].iter().map(|dv| dv.map(T::to_f64)).collect();
        self.advance_proxies(&proxy_dv);
    }

    /// Moves the simulated tools by their rows of Δv (after the nodes': each tool's, then
    /// the rows they turn on).
    pub(super) fn advance_proxies(&mut self, dv: &[Vector3<f64>]) {
        let (n, h) = (self.u.len(), self.params.dt);
        for (proxy, step) in self.proxies.iter_mut().zip(dv) {
            proxy.v += step;
            proxy.x += proxy.v * h;
            if let Some(turning) = &mut proxy.turning {
                turning.omega += dv.get(turning.row - n).copied().unwrap_or_else(Vector3::zeros);
                turning.orientation =
                    nalgebra::UnitQuaternion::from_scaled_axis(turning.omega * h) * turning.orientation;
            }
        }
    }

    pub(super) fn spmv_into(&self, p: &[Vector3<T>], out: &mut [Vector3<T>]) {
        let n = self.u.len();
        out[..n].par_iter_mut().with_min_len(CHUNK).enumerate().for_each(|(i, q)| {
            let adj = &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize];
            *q = kernels::spmv_row(i, adj, &self.terms, &self.diag[i], self.fixed[i], p);
        });
        for (k, diag) in self.proxy_diag.iter().enumerate() {
            out[n + k] = diag * p[n + k];
        }
        self.contact_product(p, out);
    }

    /// Preconditioned CG on the assembled system, warm-started from the previous Δv.
    /// Fixed nodes are filtered out (their rows of r, z and p stay zero).
    pub(crate) fn solve(&mut self) -> CgStats {
        let tol = T::of(self.params.cg_tolerance);
        for (dv, &fixed) in self.dv.iter_mut().zip(&self.fixed) {
            if fixed {
                *dv = Vector3::zeros();
            }
        }
        let b_norm2 = dot(&self.rhs, &self.rhs);
        if b_norm2 == T::zero() {
            self.dv.iter_mut().for_each(|v| *v = Vector3::zeros());
            return CgStats { iterations: 0, relative_residual: 0.0 };
        }
        let mut q = std::mem::take(&mut self.q);
        self.spmv_into(&self.dv, &mut q);
        let (rhs, precond) = (&self.rhs, &self.precond);
        (self.r.par_iter_mut(), self.z.par_iter_mut(), q.par_iter())
            .into_par_iter()
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, (r, z, q))| {
                *r = rhs[i] - q;
                *z = precond[i] * *r;
            });
        if self.amg.is_some() {
            self.z = self.apply_amg(&self.r);
        }
        self.p.clone_from(&self.z);
        let mut rz = dot(&self.r, &self.z);
        let mut rr = dot(&self.r, &self.r);
        let target = tol * tol * b_norm2;
        let mut iterations = 0;
        while rr > target && iterations < self.params.cg_max_iterations {
            // q = A p and p·q in one pass.
            self.spmv_into(&self.p, &mut q);
            let pq = dot(&self.p, &q);
            if pq <= T::zero() {
                break; // cannot happen for SPD A; guards against round-off at convergence
            }
            let alpha = rz / pq;
            // x, r, z updates and both dots in one pass.
            let partials: Vec<(T, T)> = (
                self.dv.par_chunks_mut(CHUNK),
                self.r.par_chunks_mut(CHUNK),
                self.z.par_chunks_mut(CHUNK),
                self.p.par_chunks(CHUNK),
                q.par_chunks(CHUNK),
                precond.par_chunks(CHUNK),
            )
                .into_par_iter()
                .map(|(dv, r, z, p, q, m)| {
                    let (mut rz, mut rr) = (T::zero(), T::zero());
                    for k in 0..dv.len() {
                        dv[k] += p[k] * alpha;
                        r[k] -= q[k] * alpha;
                        z[k] = m[k] * r[k];
                        rz += r[k].dot(&z[k]);
                        rr += r[k].dot(&r[k]);
                    }
                    (rz, rr)
                })
                .collect();
            let (mut rz_new, rr_new) = partials.iter().fold((T::zero(), T::zero()), |(a, b), (c, d)| (a + *c, b + *d));
            if self.amg.is_some() && rr_new > target {
                self.z = self.apply_amg(&self.r);
                rz_new = dot(&self.r, &self.z);
            }
            let beta = rz_new / rz;
            rz = rz_new;
            rr = rr_new;
            self.p.par_iter_mut().zip(self.z.par_iter()).with_min_len(CHUNK).for_each(|(p, z)| *p = z + *p * beta);
            iterations += 1;
        }
        self.q = q;
        CgStats { iterations, relative_residual: (rr / b_norm2).sqrt().to_f64() }
    }

    /// Assembled A as f64 triplets; fixed nodes keep an identity row and no couplings.
    /// With `tools`, the simulated tools' rows and the contacts' terms too (the whole
    /// system); without, the mesh's springs alone (what the multigrid hierarchy is built on).
    pub(super) fn system_triplets(&self, tools: bool) -> Vec<(usize, usize, f64)> {
        let mut triplets = Vec::with_capacity(self.adjacency.len() * 9 + self.u.len() * 9);
        for i in 0..self.u.len() {
            if self.fixed[i] {
                for c in 0..3 {
                    triplets.push((3 * i + c, 3 * i + c, 1.0));
                }
                continue;
            }
            for r in 0..3 {
                for c in 0..3 {
                    triplets.push((3 * i + r, 3 * i + c, self.diag[i][(r, c)].to_f64()));
                }
            }
            for &[j, e] in &self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize] {
                if self.fixed[j as usize] {
                    continue;
                }
                for r in 0..3 {
                    for c in 0..3 {
                        triplets.push((3 * i + r, 3 * j as usize + c, -self.terms[e as usize].block[(r, c)].to_f64()));
                    }
                }
            }
        }
        if tools {
            let n = self.u.len();
            for (k, d) in self.proxy_diag.iter().enumerate() {
                for r in 0..3 {
                    for c in 0..3 {
                        triplets.push((3 * (n + k) + r, 3 * (n + k) + c, d[(r, c)].to_f64()));
                    }
                }
            }
            for c in &self.contact_rows {
                let touched = || c.rows.iter().zip(&c.gradients).filter(|(r, _)| **r != usize::MAX);
                for (&ra, ga) in touched() {
                    for (&rb, gb) in touched() {
                        let block = (ga * gb.transpose() * c.h2k).map(T::to_f64);
                        for r in 0..3 {
                            for col in 0..3 {
                                triplets.push((3 * ra + r, 3 * rb + col, block[(r, col)]));
                            }
                        }
                    }
                }
            }
        }
        triplets
    }

    /// (Re)builds the multigrid hierarchy from the assembled matrix of this step.
    pub(super) fn build_amg(&mut self) {
        let started = std::time::Instant::now();
        let n = self.u.len();
        let a = Csr::from_triplets(3 * n, 3 * n, self.system_triplets(false));
        let neighbours: Vec<Vec<u32>> = (0..n)
            .map(|i| {
                self.adjacency[self.offsets[i] as usize..self.offsets[i + 1] as usize]
                    .iter()
                    .map(|[j, _]| *j)
                    .filter(|j| !self.fixed[*j as usize])
                    .collect()
            })
            .collect();
        let positions = self.positions_f64();
        self.amg = Amg::new(&a, &positions, &self.fixed, &neighbours).map(|mut amg| {
            amg.fine_omega = self.block_jacobi_omega();
            tracing::debug!(
                "AMG hierarchy in {:.0} ms: fine {} unknowns, coarse levels {:?}, prolongator nonzeros per level: {:?}",
                started.elapsed().as_secs_f64() * 1e3,
                3 * n,
                amg.coarse_sizes,
                amg.nonzeros()
            );
            AmgState { amg, iterations_at_build: 0, stale: false }
        });
    }

    /// Damping 4/(3 λmax) of the fine block-Jacobi smoother, λmax of D⁻¹A by power iteration.
    pub(super) fn block_jacobi_omega(&self) -> f64 {
        let n = self.rhs.len();
        let mut x: Vec<Vector3<T>> = (0..n)
            .map(|i| {
                if self.fixed.get(i).copied().unwrap_or(false) {
                    Vector3::zeros()
                } else {
                    Vector3::repeat(T::one() + T::of(((i * 7919) % 13) as f64 / 13.0))
                }
            })
            .collect();
        let mut y = vec![Vector3::zeros(); n];
        let mut lambda = 1.0;
        for _ in 0..12 {
            self.spmv_into(&x, &mut y);
            for (yi, m) in y.iter_mut().zip(&self.precond) {
                *yi = m * *yi;
            }
            let (yn, xn) = (dot(&y, &y).to_f64().sqrt(), dot(&x, &x).to_f64().sqrt());
            if yn == 0.0 || xn == 0.0 {
                break;
            }
            lambda = yn / xn;
            let inv = T::of(1.0 / yn);
            for (xi, yi) in x.iter_mut().zip(&y) {
                *xi = yi * inv;
            }
        }
        4.0 / (3.0 * lambda)
    }

    /// z = M⁻¹ r: one symmetric V-cycle, the fine level on the current block operator.
    pub(super) fn apply_amg(&self, r: &[Vector3<T>]) -> Vec<Vector3<T>> {
        let Some(state) = &self.amg else { return r.to_vec() };
        let omega = T::of(state.amg.fine_omega);
        let n = r.len();
        let mut z: Vec<Vector3<T>> =
            r.par_iter().zip(self.precond.par_iter()).with_min_len(CHUNK).map(|(r, m)| m * r * omega).collect();
        let mut az = vec![Vector3::zeros(); n];
        self.spmv_into(&z, &mut az);
        let residual: Vec<f64> = r[..self.u.len()]
            .iter()
            .zip(&az)
            .flat_map(|(r, a)| {
                let d = r - a;
                [d.x.to_f64(), d.y.to_f64(), d.z.to_f64()]
            })
            .collect();
        let e = state.amg.coarse_correction(&residual);
        z[..self.u.len()]
            .par_iter_mut()
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, zi)| *zi += Vector3::new(T::of(e[3 * i]), T::of(e[3 * i + 1]), T::of(e[3 * i + 2])));
        self.spmv_into(&z, &mut az);
        z.par_iter_mut()
            .zip(az.par_iter())
            .with_min_len(CHUNK)
            .enumerate()
            .for_each(|(i, (zi, a))| *zi += self.precond[i] * (r[i] - a) * omega);
        z
    }

    /// The assembled system as f64 triplets (row, col, value), for checks against direct solvers.
    pub fn assembled_system(&mut self) -> Result<(Triplets, Vec<f64>), SolverError> {
        let tools = self.prepare_step()?;
        self.assemble(&tools);
        let rhs = self.rhs.iter().flat_map(|v| [v.x.to_f64(), v.y.to_f64(), v.z.to_f64()]).collect();
        Ok((self.system_triplets(true), rhs))
    }

    /// The multigrid hierarchy for the step about to be solved (after `prepare_step`, with
    /// its contact `tools`), as this path builds it there: on the springs' matrix, the fine
    /// smoother's damping from the whole system (the simulated tools' rows and contacts
    /// with it). The GPU's device twin is built from it.
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn multigrid_at_step(&mut self, tools: &[ContactTool<T>]) -> Option<Amg> {
        self.assemble(tools);
        self.build_amg();
        self.amg.take().map(|state| state.amg)
    }

    /// The multigrid hierarchy in use, if any (its device twin is built from it).
    pub fn multigrid(&self) -> Option<&Amg> {
        self.amg.as_ref().map(|state| &state.amg)
    }

    /// Prepares the preconditioner in use for the assembled system (tests).
    pub fn prepare_preconditioner(&mut self) {
        if self.multigrid {
            self.build_amg();
        } else {
            self.amg = None;
        }
    }

    /// Solves the currently assembled system from a zero start and returns Δv (for tests).
    pub fn solve_assembled(&mut self) -> (Vec<Vector3<f64>>, CgStats) {
        self.dv.iter_mut().for_each(|v| *v = Vector3::zeros());
        let stats = self.solve();
        (self.dv.iter().map(|v| v.map(T::to_f64)).collect(), stats)
    }
}

/// Deterministic parallel dot product of two vector fields.
fn dot<T: Real>(a: &[Vector3<T>], b: &[Vector3<T>]) -> T {
    let partials: Vec<T> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(a, b)| a.iter().zip(b).fold(T::zero(), |s, (x, y)| s + x.dot(y)))
        .collect();
    partials.into_iter().fold(T::zero(), |s, x| s + x)
}
