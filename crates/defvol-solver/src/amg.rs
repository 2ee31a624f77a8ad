//! Smoothed-aggregation algebraic multigrid (Vaněk, Mandel, Brezina), used as the CG
//! preconditioner of the implicit step on the CPU.
//!
//! - Aggregates: nodes grouped greedily with their graph neighbours (fixed nodes excluded).
//! - Near-null space: the six rigid-body modes (3 translations, 3 rotations) of each
//!   aggregate, orthonormalised per aggregate (QR); R becomes the next level's null space.
//! - Prolongator: P = (I - ω D⁻¹A) P₀ with ω = 4 / (3 λmax(D⁻¹A)); coarse A = Pᵀ A P.
//! - Cycle: at the fine level a symmetric V-cycle step (damped block-Jacobi pre- and
//!   post-smoothing on the solver's own current operator, then the coarse correction);
//!   below it additive levels `ω D⁻¹ b + P (cycle) R b`, which never multiply by the
//!   coarse matrices (smoothed aggregation makes them the widest: ~300 nonzeros a row),
//!   and a dense Cholesky solve at the coarsest. Every part is symmetric positive-definite,
//!   so the whole is a valid CG preconditioner. More iterations than multiplicative coarse
//!   levels, each far cheaper (see docs/perf/journal.md#additive-coarse-levels).
//!
//! The hierarchy is built from the matrix of one step and reused while it keeps CG fast
//! (A changes slowly from step to step); any fixed SPD preconditioner leaves CG exact.

use nalgebra::{DMatrix, Vector3};
use rayon::prelude::*;

/// Compressed sparse rows in f64 (setup) or the solver precision (cycles).
#[derive(Debug, Clone)]
pub struct Csr {
    pub rows: usize,
    pub cols: usize,
    pub indptr: Vec<usize>,
    pub indices: Vec<u32>,
    pub values: Vec<f64>,
}

impl Csr {
    pub fn from_triplets(rows: usize, cols: usize, mut t: Vec<(usize, usize, f64)>) -> Self {
        t.sort_unstable_by_key(|&(r, c, _)| (r, c));
        let mut indptr = vec![0usize; rows + 1];
        let mut indices = Vec::with_capacity(t.len());
        let mut values: Vec<f64> = Vec::with_capacity(t.len());
        let mut last: Option<(usize, usize)> = None;
        for (r, c, v) in t {
            if last == Some((r, c)) {
                if let Some(x) = values.last_mut() {
                    *x += v;
                }
                continue;
            }
            indptr[r + 1] += 1;
            indices.push(c as u32);
            values.push(v);
            last = Some((r, c));
        }
        for r in 0..rows {
            indptr[r + 1] += indptr[r];
        }
        Self { rows, cols, indptr, indices, values }
    }

    fn row(&self, r: usize) -> (&[u32], &[f64]) {
        let span = self.indptr[r]..self.indptr[r + 1];
        (&self.indices[span.clone()], &self.values[span])
    }

    pub fn spmv(&self, x: &[f64], y: &mut [f64]) {
        y.par_iter_mut().enumerate().with_min_len(512).for_each(|(r, out)| {
            let (idx, val) = self.row(r);
            *out = idx.iter().zip(val).map(|(c, v)| v * x[*c as usize]).sum();
        });
    }

    pub fn transpose(&self) -> Self {
        let mut counts = vec![0usize; self.cols + 1];
        for &c in &self.indices {
            counts[c as usize + 1] += 1;
        }
        for c in 0..self.cols {
            counts[c + 1] += counts[c];
        }
        let mut cursor = counts.clone();
        let mut indices = vec![0u32; self.indices.len()];
        let mut values = vec![0.0; self.values.len()];
        for r in 0..self.rows {
            let (idx, val) = self.row(r);
            for (c, v) in idx.iter().zip(val) {
                let slot = &mut cursor[*c as usize];
                indices[*slot] = r as u32;
                values[*slot] = *v;
                *slot += 1;
            }
        }
        Self { rows: self.cols, cols: self.rows, indptr: counts, indices, values }
    }

    /// self · other (Gustavson, rows in parallel, each with a dense accumulator).
    pub fn matmul(&self, other: &Csr) -> Csr {
        let rows: Vec<(Vec<u32>, Vec<f64>)> = (0..self.rows)
            .into_par_iter()
            .with_min_len(256)
            .map_init(
                || (vec![0.0f64; other.cols], vec![false; other.cols]),
                |(acc, used), r| {
                    let mut cols: Vec<u32> = Vec::new();
                    let (idx, val) = self.row(r);
                    for (k, a) in idx.iter().zip(val) {
                        let (idx2, val2) = other.row(*k as usize);
                        for (c, b) in idx2.iter().zip(val2) {
                            let c = *c as usize;
                            if !used[c] {
                                used[c] = true;
                                cols.push(c as u32);
                            }
                            acc[c] += a * b;
                        }
                    }
                    cols.sort_unstable();
                    let vals = cols
                        .iter()
                        .map(|&c| {
                            let c = c as usize;
                            used[c] = false;
                            std::mem::take(&mut acc[c])
                        })
                        .collect();
                    (cols, vals)
                },
            )
            .collect();
        let mut indptr = Vec::with_capacity(self.rows + 1);
        indptr.push(0);
        let nnz: usize = rows.iter().map(|r| r.0.len()).sum();
        let (mut indices, mut values) = (Vec::with_capacity(nnz), Vec::with_capacity(nnz));
        for (c, v) in rows {
            indices.extend_from_slice(&c);
            values.extend_from_slice(&v);
            indptr.push(indices.len());
        }
        Csr { rows: self.rows, cols: other.cols, indptr, indices, values }
    }

    fn diagonal(&self) -> Vec<f64> {
        (0..self.rows)
            .map(|r| {
                let (idx, val) = self.row(r);
                idx.iter().zip(val).find(|(c, _)| **c as usize == r).map_or(1.0, |(_, v)| *v)
            })
            .collect()
    }
}

/// The cycle-time form of a [`Csr`]: f32 values (half the memory traffic; the cycle is a
/// preconditioner, so its rounding does not limit CG's accuracy), f64 accumulation.
#[derive(Debug, Clone)]
pub struct CsrF32 {
    pub(crate) rows: usize,
    pub(crate) indptr: Vec<u32>,
    pub(crate) indices: Vec<u32>,
    pub(crate) values: Vec<f32>,
}

impl From<&Csr> for CsrF32 {
    fn from(m: &Csr) -> Self {
        Self {
            rows: m.rows,
            indptr: m.indptr.iter().map(|&p| p as u32).collect(),
            indices: m.indices.clone(),
            values: m.values.iter().map(|&v| v as f32).collect(),
        }
    }
}

impl CsrF32 {
    pub fn spmv(&self, x: &[f64], y: &mut [f64]) {
        y.par_iter_mut().enumerate().with_min_len(512).for_each(|(r, out)| {
            let span = self.indptr[r] as usize..self.indptr[r + 1] as usize;
            *out = self.indices[span.clone()]
                .iter()
                .zip(&self.values[span])
                .map(|(c, v)| *v as f64 * x[*c as usize])
                .sum();
        });
    }
}

/// Largest eigenvalue of D⁻¹A by power iteration (enough for smoothing weights).
fn lambda_max(a: &Csr, dinv: &[f64]) -> f64 {
    let n = a.rows;
    let mut x: Vec<f64> = (0..n).map(|i| 1.0 + ((i * 7919) % 13) as f64 / 13.0).collect();
    let mut y = vec![0.0; n];
    let mut lambda = 1.0;
    for _ in 0..15 {
        a.spmv(&x, &mut y);
        for (yi, d) in y.iter_mut().zip(dinv) {
            *yi *= d;
        }
        let norm = y.iter().map(|v| v * v).sum::<f64>().sqrt();
        let xnorm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm == 0.0 || xnorm == 0.0 {
            break;
        }
        lambda = norm / xnorm;
        for (xi, yi) in x.iter_mut().zip(&y) {
            *xi = yi / norm;
        }
    }
    lambda
}

/// Greedy aggregation of the "nodes" of a graph; `None` for excluded nodes.
fn aggregate(neighbours: &[Vec<u32>], excluded: &[bool]) -> (Vec<Option<u32>>, usize) {
    let n = neighbours.len();
    let mut agg: Vec<Option<u32>> = vec![None; n];
    let mut count = 0u32;
    // Pass 1: a node whose neighbours are all free roots an aggregate with them.
    for i in 0..n {
        if excluded[i] || agg[i].is_some() {
            continue;
        }
        if neighbours[i].iter().all(|&j| agg[j as usize].is_none() || excluded[j as usize]) {
            agg[i] = Some(count);
            for &j in &neighbours[i] {
                if !excluded[j as usize] {
                    agg[j as usize] = Some(count);
                }
            }
            count += 1;
        }
    }
    // Pass 2: the rest join a neighbouring aggregate; pass 3: leftovers group together.
    let pass1 = agg.clone();
    for i in 0..n {
        if excluded[i] || agg[i].is_some() {
            continue;
        }
        agg[i] = neighbours[i].iter().find_map(|&j| pass1[j as usize]);
    }
    for i in 0..n {
        if excluded[i] || agg[i].is_some() {
            continue;
        }
        agg[i] = Some(count);
        for &j in &neighbours[i] {
            if !excluded[j as usize] && agg[j as usize].is_none() {
                agg[j as usize] = Some(count);
            }
        }
        count += 1;
    }
    (agg, count as usize)
}

/// Tentative prolongator: per aggregate, QR of the stacked null-space rows.
/// `dofs[node]` lists the node's rows; `nullspace` has one row of `modes` values per row.
fn tentative(
    rows: usize,
    dofs: &[Vec<usize>],
    agg: &[Option<u32>],
    count: usize,
    nullspace: &DMatrix<f64>,
) -> (Csr, Vec<Vec<usize>>, DMatrix<f64>) {
    let modes = nullspace.ncols();
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
    for (node, a) in agg.iter().enumerate() {
        if let Some(a) = a {
            members[*a as usize].push(node);
        }
    }
    let mut triplets = Vec::new();
    let mut coarse_dofs: Vec<Vec<usize>> = Vec::with_capacity(count);
    let mut coarse_rows: Vec<Vec<f64>> = Vec::new();
    let mut next = 0usize;
    for nodes in &members {
        let local_rows: Vec<usize> = nodes.iter().flat_map(|n| dofs[*n].iter().copied()).collect();
        let mut block = DMatrix::<f64>::zeros(local_rows.len(), modes);
        for (k, &r) in local_rows.iter().enumerate() {
            block.set_row(k, &nullspace.row(r));
        }
        let qr = block.qr();
        let (q, r) = (qr.q(), qr.r());
        let scale = r.diagonal().iter().fold(0.0f64, |m, d| m.max(d.abs()));
        // Keep the modes this aggregate resolves (fewer for tiny or collinear aggregates).
        let kept: Vec<usize> = (0..modes.min(local_rows.len())).filter(|&c| r[(c, c)].abs() > 1e-8 * scale).collect();
        let mut mine = Vec::with_capacity(kept.len());
        for &c in &kept {
            for (k, &row) in local_rows.iter().enumerate() {
                let v = q[(k, c)];
                if v != 0.0 {
                    triplets.push((row, next, v));
                }
            }
            let mut coarse_row = vec![0.0; modes];
            for (m, slot) in coarse_row.iter_mut().enumerate() {
                *slot = r[(c, m)];
            }
            coarse_rows.push(coarse_row);
            mine.push(next);
            next += 1;
        }
        coarse_dofs.push(mine);
    }
    let p0 = Csr::from_triplets(rows, next, triplets);
    let b = DMatrix::from_fn(next, modes, |r, c| coarse_rows[r][c]);
    (p0, coarse_dofs, b)
}

pub(crate) struct Level {
    pub(crate) p: CsrF32,
    pub(crate) r: CsrF32,
    pub(crate) dinv: Vec<f64>,
    pub(crate) omega: f64,
}

/// The hierarchy below the fine level plus the coarsest factor.
pub struct Amg {
    /// Fine → first coarse prolongator and its transpose.
    pub(crate) p: CsrF32,
    pub(crate) r: CsrF32,
    pub(crate) levels: Vec<Level>,
    coarsest: Option<nalgebra::Cholesky<f64, nalgebra::Dyn>>,
    coarsest_a: Csr,
    /// Damping of the fine block-Jacobi smoother.
    pub fine_omega: f64,
    pub coarse_sizes: Vec<usize>,
}

/// Whether a hierarchy has gone stale: a solve with it needed more than twice the
/// iterations of its first solve, and 4 more (the matrix has drifted from the one it was
/// built from). Both backends rebuild by this rule.
pub fn is_stale(iterations_at_build: u32, iterations: u32) -> bool {
    iterations > 2 * iterations_at_build + 4
}

/// Coarsening stops below this many unknowns; the rest is solved directly.
const COARSEST: usize = 600;

impl Amg {
    /// Builds the hierarchy for the fine matrix `a` (3 rows per node, node-major),
    /// `positions` for the rigid-body modes, `fixed` nodes excluded from aggregation,
    /// `neighbours` the node graph, `block_dinv_lambda` λmax of (block D)⁻¹A.
    pub fn new(a: &Csr, positions: &[Vector3<f64>], fixed: &[bool], neighbours: &[Vec<u32>]) -> Option<Self> {
        let n = positions.len();
        let centroid = positions.iter().sum::<Vector3<f64>>() / n.max(1) as f64;
        let scale = positions.iter().map(|p| (p - centroid).norm()).fold(0.0, f64::max).max(f64::MIN_POSITIVE);
        // Rigid-body modes, rotations scaled to the body's size for a balanced QR.
        let nullspace = DMatrix::from_fn(3 * n, 6, |row, mode| {
            let (node, axis) = (row / 3, row % 3);
            let p = (positions[node] - centroid) / scale;
            match mode {
                0..=2 => f64::from(u8::from(axis == mode)),
                3 => [0.0, -p.z, p.y][axis],
                4 => [p.z, 0.0, -p.x][axis],
                _ => [-p.y, p.x, 0.0][axis],
            }
        });
        let dofs: Vec<Vec<usize>> = (0..n).map(|i| vec![3 * i, 3 * i + 1, 3 * i + 2]).collect();
        let (agg, count) = aggregate(neighbours, fixed);
        if count == 0 {
            return None;
        }
        let (p0, mut coarse_dofs, mut b) = tentative(3 * n, &dofs, &agg, count, &nullspace);
        let dinv: Vec<f64> = a.diagonal().iter().map(|d| 1.0 / d).collect();
        let p = smooth_prolongator(a, &p0, &dinv);
        let r = p.transpose();
        let mut coarse = r.matmul(&a.matmul(&p));
        let fine_omega = 1.0;
        let mut levels = Vec::new();
        let mut coarse_sizes = vec![coarse.rows];
        while coarse.rows > COARSEST {
            // Coarse "nodes" are aggregates; they neighbour where the coarse matrix couples them.
            let node_of: Vec<usize> = {
                let mut v = vec![0usize; coarse.rows];
                for (node, ds) in coarse_dofs.iter().enumerate() {
                    for d in ds {
                        v[*d] = node;
                    }
                }
                v
            };
            let nodes = coarse_dofs.len();
            let mut graph: Vec<Vec<u32>> = vec![Vec::new(); nodes];
            for (node, ds) in coarse_dofs.iter().enumerate() {
                for &d in ds {
                    let (idx, _) = coarse.row(d);
                    for &c in idx {
                        let other = node_of[c as usize];
                        if other != node && !graph[node].contains(&(other as u32)) {
                            graph[node].push(other as u32);
                        }
                    }
                }
            }
            let (agg, count) = aggregate(&graph, &vec![false; nodes]);
            if count == 0 || count == nodes {
                break;
            }
            let (p0, next_dofs, next_b) = tentative(coarse.rows, &coarse_dofs, &agg, count, &b);
            let dinv: Vec<f64> = coarse.diagonal().iter().map(|d| 1.0 / d).collect();
            let p = smooth_prolongator(&coarse, &p0, &dinv);
            let r = p.transpose();
            let next = r.matmul(&coarse.matmul(&p));
            let omega = 4.0 / (3.0 * lambda_max(&coarse, &dinv));
            levels.push(Level { p: CsrF32::from(&p), r: CsrF32::from(&r), dinv, omega });
            coarse_sizes.push(next.rows);
            coarse = next;
            coarse_dofs = next_dofs;
            b = next_b;
        }
        let dense = DMatrix::from_fn(coarse.rows, coarse.rows, |_, _| 0.0);
        let mut dense = dense;
        for row in 0..coarse.rows {
            let (idx, val) = coarse.row(row);
            for (c, v) in idx.iter().zip(val) {
                dense[(row, *c as usize)] = *v;
            }
        }
        let coarsest = dense.cholesky();
        Some(Self {
            p: CsrF32::from(&p),
            r: CsrF32::from(&r),
            levels,
            coarsest,
            coarsest_a: coarse,
            fine_omega,
            coarse_sizes,
        })
    }

    /// Solves (approximately) the first coarse level's system A_c e = rc by a V-cycle.
    fn coarse_cycle(&self, level: usize, rhs: &[f64]) -> Vec<f64> {
        if level == self.levels.len() {
            return match &self.coarsest {
                Some(chol) => chol.solve(&nalgebra::DVector::from_column_slice(rhs)).as_slice().to_vec(),
                // Not positive-definite (cannot happen for SPD A): fall back to Jacobi.
                None => rhs.iter().zip(self.coarsest_a.diagonal()).map(|(r, d)| r / d).collect(),
            };
        }
        let l = &self.levels[level];
        // Additive at coarse levels: ω D⁻¹ b + P (cycle) R b. No products with the level's
        // own matrix (the widest one of the hierarchy), still symmetric positive-definite.
        let mut rc = vec![0.0; l.r.rows];
        l.r.spmv(rhs, &mut rc);
        let ec = self.coarse_cycle(level + 1, &rc);
        let mut x = vec![0.0; rhs.len()];
        l.p.spmv(&ec, &mut x);
        for ((xi, b), d) in x.iter_mut().zip(rhs).zip(&l.dinv) {
            *xi += l.omega * b * d;
        }
        x
    }

    /// The coarse-grid correction of the fine level: P (A_c⁻¹ by V-cycle) Pᵀ r.
    pub fn coarse_correction(&self, residual: &[f64]) -> Vec<f64> {
        let mut rc = vec![0.0; self.r.rows];
        self.r.spmv(residual, &mut rc);
        let ec = self.coarse_cycle(0, &rc);
        let mut e = vec![0.0; self.p.rows];
        self.p.spmv(&ec, &mut e);
        e
    }

    /// The coarsest level's solve as a dense inverse (the device applies it as one product;
    /// the Jacobi fallback's diagonal where the factor failed, as the CPU cycle does).
    pub fn coarsest_inverse(&self) -> DMatrix<f64> {
        match &self.coarsest {
            Some(chol) => chol.inverse(),
            None => DMatrix::from_diagonal(&nalgebra::DVector::from_iterator(
                self.coarsest_a.rows,
                self.coarsest_a.diagonal().into_iter().map(|d| 1.0 / d),
            )),
        }
    }

    /// Nonzeros of the cycle's operators (for logs: they set its cost).
    pub fn nonzeros(&self) -> Vec<usize> {
        let mut v = vec![self.p.values.len()];
        v.extend(self.levels.iter().map(|l| l.p.values.len()));
        v
    }
}

fn smooth_prolongator(a: &Csr, p0: &Csr, dinv: &[f64]) -> Csr {
    let omega = 4.0 / (3.0 * lambda_max(a, dinv));
    let ap0 = a.matmul(p0);
    // P = P0 - ω D⁻¹ A P0: same pattern as A P0 plus P0's.
    let mut t = Vec::with_capacity(ap0.values.len() + p0.values.len());
    for r in 0..ap0.rows {
        let (idx, val) = ap0.row(r);
        for (c, v) in idx.iter().zip(val) {
            t.push((r, *c as usize, -omega * dinv[r] * v));
        }
        let (idx, val) = p0.row(r);
        for (c, v) in idx.iter().zip(val) {
            t.push((r, *c as usize, *v));
        }
    }
    Csr::from_triplets(a.rows, p0.cols, t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matmul_and_transpose_match_dense() {
        let a = Csr::from_triplets(
            3,
            4,
            vec![(0, 0, 1.0), (0, 3, 2.0), (1, 1, -1.0), (2, 0, 3.0), (2, 2, 4.0), (0, 0, 0.5)],
        );
        let b = Csr::from_triplets(4, 2, vec![(0, 0, 1.0), (1, 1, 2.0), (2, 0, -1.0), (3, 1, 5.0)]);
        let dense = |m: &Csr| {
            let mut d = DMatrix::<f64>::zeros(m.rows, m.cols);
            for r in 0..m.rows {
                let (idx, val) = m.row(r);
                for (c, v) in idx.iter().zip(val) {
                    d[(r, *c as usize)] += v;
                }
            }
            d
        };
        assert_eq!(dense(&a.matmul(&b)), dense(&a) * dense(&b));
        assert_eq!(dense(&a.transpose()), dense(&a).transpose());
    }
}
