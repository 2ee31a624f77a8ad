//! Per-element kernels of the solver, written once for the CPU and kept line-by-line
//! comparable with `solver.wgsl` (same names, same order of operations).
//!
//! Sign conventions: spring e joins (a, b); `force` is the force on a (the force on b is
//! its negative); `kv` is K_e (v_b - v_a). The system (seed eq. 9, Baraff-Witkin) is
//! `(M - h ∂f/∂v - h² ∂f/∂x) Δv = h (f + h ∂f/∂x v)`, assembled per node by gathering
//! its springs, so neither backend needs atomic adds.
//!
//! **Indefiniteness.** The exact stiffness block is `k [u uᵀ + (1 - L/l)(I - u uᵀ)]`; for
//! a compressed spring (l < L) the transverse term is negative and A can lose definiteness,
//! which breaks CG. We clamp `1 - L/l` at 0 (as Choi & Ko do), so every block is PSD and A
//! = M + PSD is symmetric positive-definite for any state. The force itself stays exact.

use nalgebra::{Matrix3, Vector3};

use defvol_core::math::Real;

/// Per-spring quantities of one implicit step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpringTerms<T: Real> {
    pub force: Vector3<T>,
    pub kv: Vector3<T>,
    /// A_e = h D_e + h² K_e: the off-diagonal block of A is -A_e.
    pub block: Matrix3<T>,
}

/// Spring force on node a (elastic + damping along the spring); `edge` is x_b - x_a,
/// formed by the caller as rest edge + (u_b - u_a).
#[inline]
pub fn spring_force<T: Real>(
    edge: &Vector3<T>,
    va: &Vector3<T>,
    vb: &Vector3<T>,
    rest: T,
    k: T,
    damping: T,
) -> Vector3<T> {
    let d = *edge;
    let l = d.norm();
    if l <= T::default_epsilon() {
        return Vector3::zeros();
    }
    let u = d / l;
    u * (k * (l - rest) + damping * (vb - va).dot(&u))
}

#[inline]
#[allow(clippy::too_many_arguments)]
pub fn spring_terms<T: Real>(
    edge: &Vector3<T>,
    va: &Vector3<T>,
    vb: &Vector3<T>,
    rest: T,
    k: T,
    damping: T,
    h: T,
) -> SpringTerms<T> {
    let d = *edge;
    let l = d.norm();
    if l <= T::default_epsilon() {
        return SpringTerms { force: Vector3::zeros(), kv: Vector3::zeros(), block: Matrix3::zeros() };
    }
    let u = d / l;
    let dv = vb - va;
    let force = u * (k * (l - rest) + damping * dv.dot(&u));
    let uu = u * u.transpose();
    let geometric = (T::one() - rest / l).max(T::zero());
    let stiffness_block = uu * k + (Matrix3::identity() - uu) * (k * geometric);
    let kv = stiffness_block * dv;
    let block = uu * (h * damping) + stiffness_block * (h * h);
    SpringTerms { force, kv, block }
}

/// Penalty contact of one tool on a node: (force, n nᵀ · k_c) when inside.
#[inline]
pub fn contact<T: Real>(
    p: &Vector3<T>,
    a: &Vector3<T>,
    b: &Vector3<T>,
    radius: T,
    stiffness: T,
) -> Option<(Vector3<T>, Matrix3<T>)> {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let t = if len2 > T::zero() { ((p - a).dot(&ab) / len2).clamp(T::zero(), T::one()) } else { T::zero() };
    let d = p - (a + ab * t);
    let dist = d.norm();
    if dist >= radius {
        return None;
    }
    let n = if dist > T::of(1e-12) { d / dist } else { Vector3::z() };
    Some((n * (stiffness * (radius - dist)), n * n.transpose() * stiffness))
}

/// Tool description in the simulation's precision.
#[derive(Debug, Clone, Copy)]
pub struct ContactTool<T: Real> {
    pub a: Vector3<T>,
    pub b: Vector3<T>,
    pub radius: T,
    pub stiffness: T,
}

/// Right-hand side, diagonal block and block-Jacobi inverse of node i.
#[derive(Debug, Clone, Copy)]
pub struct NodeTerms<T: Real> {
    pub force: Vector3<T>,
    pub rhs: Vector3<T>,
    pub diag: Matrix3<T>,
    pub precond: Matrix3<T>,
}

/// Gathers node i's springs, gravity, external and contact forces into its row of A Δv = b.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn node_terms<T: Real>(
    i: usize,
    adjacency: &[[u32; 2]],
    springs: &[[u32; 2]],
    terms: &[SpringTerms<T>],
    mass: T,
    fixed: bool,
    x: &Vector3<T>,
    v: &Vector3<T>,
    external: &Vector3<T>,
    gravity: &Vector3<T>,
    tools: &[ContactTool<T>],
    h: T,
) -> NodeTerms<T> {
    let mut force = gravity * mass + external;
    let mut diag = Matrix3::identity() * mass;
    let mut kv = Vector3::zeros();
    for &[_, e] in adjacency {
        let s = &terms[e as usize];
        if springs[e as usize][0] as usize == i {
            force += s.force;
            kv += s.kv;
        } else {
            force -= s.force;
            kv -= s.kv;
        }
        diag += s.block;
    }
    for tool in tools {
        if let Some((f, nn)) = contact(x, &tool.a, &tool.b, tool.radius, tool.stiffness) {
            force += f;
            diag += nn * (h * h);
            kv -= nn * v;
        }
    }
    if fixed {
        return NodeTerms { force, rhs: Vector3::zeros(), diag, precond: Matrix3::zeros() };
    }
    let rhs = (force + kv * h) * h;
    let precond = diag.try_inverse().unwrap_or_else(Matrix3::zeros);
    NodeTerms { force, rhs, diag, precond }
}

/// Row i of q = A p: the diagonal block minus the spring blocks of its neighbours.
#[inline]
pub fn spmv_row<T: Real>(
    i: usize,
    adjacency: &[[u32; 2]],
    blocks: &[SpringTerms<T>],
    diag: &Matrix3<T>,
    fixed: bool,
    p: &[Vector3<T>],
) -> Vector3<T> {
    if fixed {
        return Vector3::zeros();
    }
    let mut q = diag * p[i];
    for &[j, e] in adjacency {
        q -= blocks[e as usize].block * p[j as usize];
    }
    q
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// The analytic Jacobian of the spring force matches central differences (when stretched,
    /// where no clamping happens).
    #[test]
    fn spring_block_is_the_force_jacobian_when_stretched() {
        let xa = Vector3::new(0.0, 0.0, 0.0);
        let xb = Vector3::new(1.3, 0.2, -0.1);
        let z = Vector3::zeros();
        let (rest, k) = (1.0, 50.0);
        let t = spring_terms(&(xb - xa), &z, &z, rest, k, 0.0, 1.0);
        let eps = 1e-6;
        for c in 0..3 {
            let mut p = xb;
            p[c] += eps;
            let fp = spring_force(&(p - xa), &z, &z, rest, k, 0.0);
            p[c] -= 2.0 * eps;
            let fm = spring_force(&(p - xa), &z, &z, rest, k, 0.0);
            let col = (fp - fm) / (2.0 * eps);
            // h = 1: block = K; ∂f_a/∂x_b = K.
            assert_relative_eq!(col, t.block.column(c).into_owned(), epsilon = 1e-6);
        }
    }

    #[test]
    fn compressed_spring_block_stays_positive_semidefinite() {
        let t =
            spring_terms(&Vector3::new(0.5f64, 0.1, 0.0), &Vector3::zeros(), &Vector3::zeros(), 1.0, 100.0, 0.0, 1.0);
        let eig = t.block.symmetric_eigenvalues();
        assert!(eig.iter().all(|e| *e >= -1e-12), "{eig}");
        assert_relative_eq!(t.block, t.block.transpose());
    }
}
