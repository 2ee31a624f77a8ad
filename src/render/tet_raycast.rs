//! The tetrahedral-mesh raycaster (seed 000, section 5), CPU path: rays enter through the
//! mesh's front-facing boundary faces and walk face neighbours, leaving each tet through the
//! face with the smallest ray parameter ahead; the scalar is linear inside each tet (a
//! gradient per tet), so each segment is integrated from its entry and exit values. A ray
//! that leaves a non-convex mesh re-enters at its next boundary hit. Face planes and
//! gradients are refreshed with [`TetRaycaster::update`] after every deformation step.

use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;

use super::camera::{Camera, Projection};
use super::transfer::{Tables, TransferFunction};
use super::{RenderError, Rendered};
use crate::mesh::{TetMesh, TET_FACES};

#[derive(Debug, Clone, PartialEq)]
pub struct TetRaycastParams {
    /// Longest sub-step a segment is integrated in (world units).
    pub step: f64,
    pub early_termination: f64,
    pub background: [f64; 4],
}

impl Default for TetRaycastParams {
    fn default() -> Self {
        Self { step: 1.0, early_termination: 0.999, background: [0.0, 0.0, 0.0, 1.0] }
    }
}

/// Per tet: outward face planes (n, n·x on the face) and the scalar's gradient and offset.
#[derive(Debug, Clone, Copy, Default)]
struct TetGeometry {
    planes: [[f64; 4]; 4],
    gradient: [f64; 4],
}

pub struct TetRaycaster<'a> {
    mesh: &'a TetMesh,
    scalars: Vec<f32>,
    positions: Vec<Vector3<f64>>,
    geometry: Vec<TetGeometry>,
    /// Boundary faces as (tet, face).
    boundary: Vec<(u32, u8)>,
    tables: Tables,
    params: TetRaycastParams,
}

/// A boundary face ready for rasterising: corners, pixel box (x0, x1, y0, y1), and the
/// entry it makes.
struct ProjectedFace {
    corners: [Vector3<f64>; 3],
    pixels: (usize, usize, usize, usize),
    entry: Entry,
}

/// One boundary crossing into the mesh along a pixel's ray.
#[derive(Debug, Clone, Copy)]
struct Entry {
    t: f64,
    tet: u32,
    face: u8,
}

impl<'a> TetRaycaster<'a> {
    /// `scalars`: one value per node (the values the transfer function maps).
    pub fn new(mesh: &'a TetMesh, scalars: &[f32], tf: &TransferFunction, params: &TetRaycastParams) -> Result<Self, RenderError> {
        if scalars.len() != mesh.nodes().len() || scalars.iter().any(|s| !s.is_finite()) {
            return Err(RenderError::Parameter(format!("{} scalars for {} nodes (all must be finite)", scalars.len(), mesh.nodes().len())));
        }
        if !(params.step.is_finite() && params.step > 0.0) {
            return Err(RenderError::Parameter(format!("step {} must be finite and > 0", params.step)));
        }
        let range = scalars.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), s| (lo.min(*s), hi.max(*s)));
        let tf = tf.resolve(range)?;
        let boundary = mesh.neighbours().iter().enumerate().flat_map(|(t, n)| (0..4u8).filter(move |&k| n[k as usize] < 0).map(move |k| (t as u32, k))).collect();
        let mut raycaster = Self { mesh, scalars: scalars.to_vec(), positions: Vec::new(), geometry: Vec::new(), boundary, tables: Tables::new(&tf, range, params.step, false), params: params.clone() };
        raycaster.update(mesh.nodes())?;
        Ok(raycaster)
    }

    /// New node positions (a deformation step): face planes and gradients recomputed.
    pub fn update(&mut self, positions: &[Vector3<f64>]) -> Result<(), RenderError> {
        if positions.len() != self.mesh.nodes().len() || positions.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(RenderError::Parameter(format!("{} positions for {} nodes (all must be finite)", positions.len(), self.mesh.nodes().len())));
        }
        self.positions = positions.to_vec();
        let scalars = &self.scalars;
        self.geometry = self
            .mesh
            .tets()
            .par_iter()
            .map(|tet| {
                let x = tet.map(|i| positions[i as usize]);
                let mut g = TetGeometry::default();
                for (k, face) in TET_FACES.iter().enumerate() {
                    let (a, b, c) = (x[face[0]], x[face[1]], x[face[2]]);
                    let mut n = (b - a).cross(&(c - a));
                    // Outward: away from the opposite vertex (inverted tets stay consistent).
                    if n.dot(&(x[k] - a)) > 0.0 {
                        n = -n;
                    }
                    let n = n.try_normalize(1e-300).unwrap_or_else(Vector3::zeros);
                    g.planes[k] = [n.x, n.y, n.z, n.dot(&a)];
                }
                let s = tet.map(|i| f64::from(scalars[i as usize]));
                let m = Matrix3::from_rows(&[(x[1] - x[0]).transpose(), (x[2] - x[0]).transpose(), (x[3] - x[0]).transpose()]);
                let grad = m.try_inverse().map_or_else(Vector3::zeros, |inv| inv * Vector3::new(s[1] - s[0], s[2] - s[0], s[3] - s[0]));
                let offset = if grad == Vector3::zeros() { (s[0] + s[1] + s[2] + s[3]) / 4.0 } else { s[0] - grad.dot(&x[0]) };
                g.gradient = [grad.x, grad.y, grad.z, offset];
                g
            })
            .collect();
        Ok(())
    }

    fn scalar(&self, tet: u32, p: &Vector3<f64>) -> f32 {
        let g = self.geometry[tet as usize].gradient;
        (g[0] * p.x + g[1] * p.y + g[2] * p.z + g[3]) as f32
    }

    /// Front-facing boundary hits of every pixel's ray, nearest first: boundary faces
    /// projected to the image, each pixel centre in their box tested exactly.
    fn entries(&self, camera: &Camera) -> Vec<Vec<Entry>> {
        let (w, h) = (camera.width, camera.height);
        let camera_from_world = camera.world_from_camera.inverse();
        // Pixel box of a face; the whole image when a vertex is not in front of the camera.
        let pixel_box = |pts: &[Vector3<f64>; 3]| -> (usize, usize, usize, usize) {
            let aspect = w as f64 / h as f64;
            let mut lo = [f64::INFINITY; 2];
            let mut hi = [f64::NEG_INFINITY; 2];
            for p in pts {
                let c = camera_from_world * Point3::from(*p);
                let (u, v) = match camera.projection {
                    Projection::Perspective { fov_y_deg } => {
                        if c.z <= 1e-9 {
                            return (0, w, 0, h);
                        }
                        let t = (fov_y_deg.to_radians() / 2.0).tan();
                        (c.x / c.z / (t * aspect), c.y / c.z / t)
                    }
                    Projection::Orthographic { height } => (c.x / (height / 2.0 * aspect), c.y / (height / 2.0)),
                };
                let (px, py) = ((u + 1.0) / 2.0 * w as f64 - 0.5, (v + 1.0) / 2.0 * h as f64 - 0.5);
                lo = [lo[0].min(px), lo[1].min(py)];
                hi = [hi[0].max(px), hi[1].max(py)];
            }
            let clamp = |v: f64, n: usize| v.max(0.0).min(n as f64) as usize;
            (clamp(lo[0].floor(), w), clamp(hi[0].ceil() + 1.0, w), clamp(lo[1].floor(), h), clamp(hi[1].ceil() + 1.0, h))
        };
        let faces: Vec<ProjectedFace> = self
            .boundary
            .iter()
            .map(|&(tet, k)| {
                let nodes = self.mesh.tets()[tet as usize];
                let corners = TET_FACES[k as usize].map(|i| self.positions[nodes[i] as usize]);
                ProjectedFace { pixels: pixel_box(&corners), corners, entry: Entry { t: 0.0, tet, face: k } }
            })
            .collect();
        let mut rows: Vec<Vec<usize>> = vec![Vec::new(); h];
        for (f, face) in faces.iter().enumerate() {
            for row in &mut rows[face.pixels.2..face.pixels.3] {
                row.push(f);
            }
        }
        rows.par_iter()
            .enumerate()
            .flat_map_iter(|(py, row)| {
                let mut pixels: Vec<Vec<Entry>> = vec![Vec::new(); w];
                for &f in row {
                    let ProjectedFace { corners: pts, pixels: (x0, x1, _, _), entry } = &faces[f];
                    let plane = self.geometry[entry.tet as usize].planes[entry.face as usize];
                    for (px, pixel) in pixels.iter_mut().enumerate().take(*x1).skip(*x0) {
                        let (o, d) = camera.ray(px, py);
                        if Vector3::new(plane[0], plane[1], plane[2]).dot(&d) >= 0.0 {
                            continue; // back-facing: an exit, not an entry
                        }
                        if let Some(t) = ray_triangle(&o.coords, &d, pts) {
                            pixel.push(Entry { t, ..*entry });
                        }
                    }
                }
                for pixel in &mut pixels {
                    pixel.sort_by(|a, b| a.t.total_cmp(&b.t));
                }
                pixels
            })
            .collect()
    }

    /// One frame seen by `camera`.
    pub fn render(&self, camera: &Camera) -> Result<Rendered, RenderError> {
        camera.validate()?;
        let entries = self.entries(camera);
        let (w, h) = (camera.width, camera.height);
        let pixels: Vec<([f32; 4], f32)> = entries.par_iter().enumerate().map(|(i, list)| self.cast(camera, i % w, i / w, list)).collect();
        let rgba = pixels.iter().flat_map(|(c, _)| c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)).collect();
        let depth = pixels.iter().map(|(_, d)| *d).collect();
        Ok(Rendered { width: w, height: h, rgba, depth })
    }

    fn cast(&self, camera: &Camera, px: usize, py: usize, entries: &[Entry]) -> ([f32; 4], f32) {
        let (o, d) = camera.ray(px, py);
        let o = o.coords;
        let neighbours = self.mesh.neighbours();
        let termination = self.params.early_termination as f32;
        let mut acc = [0.0f32; 4];
        let mut depth = f32::INFINITY;
        let mut left_at = f64::NEG_INFINITY;
        'entries: for entry in entries {
            if entry.t < left_at - 1e-9 {
                continue;
            }
            let (mut tet, mut face_in, mut t_in) = (entry.tet, entry.face, entry.t);
            // A ray through an edge or a vertex can circle the tets around it without moving
            // on: a walk that stalls that long is abandoned (the next entry takes over).
            let mut stalled = 0;
            for _ in 0..4 * self.mesh.tets().len().max(1) {
                let planes = self.geometry[tet as usize].planes;
                let mut exit: Option<(f64, usize)> = None;
                for (k, plane) in planes.iter().enumerate() {
                    if k == face_in as usize {
                        continue;
                    }
                    let denom = plane[0] * d.x + plane[1] * d.y + plane[2] * d.z;
                    if denom <= 1e-15 {
                        continue;
                    }
                    let t = (plane[3] - (plane[0] * o.x + plane[1] * o.y + plane[2] * o.z)) / denom;
                    if exit.is_none_or(|(best, _)| t < best) {
                        exit = Some((t, k));
                    }
                }
                let Some((t_exit, k_exit)) = exit else { break };
                let t_out = t_exit.max(t_in);
                stalled = if t_out - t_in <= 1e-9 * (1.0 + t_in.abs()) { stalled + 1 } else { 0 };
                if stalled > 64 {
                    left_at = t_out;
                    break;
                }
                let (s_in, s_out) = (self.scalar(tet, &(o + d * t_in)), self.scalar(tet, &(o + d * t_out)));
                self.integrate(&mut acc, &mut depth, t_in, t_out, s_in, s_out);
                if acc[3] >= termination {
                    break 'entries;
                }
                let next = neighbours[tet as usize][k_exit];
                if next < 0 {
                    left_at = t_out;
                    break;
                }
                let Some(back) = neighbours[next as usize].iter().position(|&n| n == tet as i32) else { break };
                (tet, face_in, t_in) = (next as u32, back as u8, t_out);
            }
        }
        let bg = self.params.background.map(|c| c as f32);
        let rest = 1.0 - acc[3];
        ([acc[0] + rest * bg[0] * bg[3], acc[1] + rest * bg[1] * bg[3], acc[2] + rest * bg[2] * bg[3], acc[3] + rest * bg[3]], depth)
    }

    /// The segment [t0, t1] with the scalar linear from s0 to s1, in midpoint sub-steps no
    /// longer than the step.
    fn integrate(&self, acc: &mut [f32; 4], depth: &mut f32, t0: f64, t1: f64, s0: f32, s1: f32) {
        let len = (t1 - t0) as f32;
        if len <= 0.0 {
            return;
        }
        let n = ((len / self.params.step as f32).ceil() as usize).clamp(1, 1 << 16);
        let ds = len / n as f32;
        for m in 0..n {
            let f = (m as f32 + 0.5) / n as f32;
            let e = self.tables.sample(s0 + (s1 - s0) * f);
            let alpha = 1.0 - (-e[3] * ds).exp();
            if alpha <= 0.0 {
                continue;
            }
            let weight = 1.0 - acc[3];
            for c in 0..3 {
                acc[c] += weight * e[c] * alpha;
            }
            acc[3] += weight * alpha;
            if depth.is_infinite() && acc[3] >= 0.5 {
                *depth = t0 as f32 + f * len;
            }
        }
    }
}

/// Möller-Trumbore: the ray parameter where it crosses the triangle (edges included).
fn ray_triangle(o: &Vector3<f64>, d: &Vector3<f64>, pts: &[Vector3<f64>; 3]) -> Option<f64> {
    let (e1, e2) = (pts[1] - pts[0], pts[2] - pts[0]);
    let p = d.cross(&e2);
    let det = e1.dot(&p);
    if det.abs() < 1e-300 {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - pts[0];
    let u = s.dot(&p) * inv;
    let q = s.cross(&e1);
    let v = d.dot(&q) * inv;
    let eps = 1e-12;
    if u < -eps || v < -eps || u + v > 1.0 + eps {
        return None;
    }
    let t = e2.dot(&q) * inv;
    (t >= 0.0).then_some(t)
}
