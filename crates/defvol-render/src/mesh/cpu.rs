//! The tetrahedral-mesh raycaster (seed 000, section 5), CPU path, line by line the twin of
//! `tet_raycast.wgsl` beside it:
//! - boundary faces are binned into 8x8-pixel tiles (`bin_boundary`; only those facing the
//!   camera when the mesh lies wholly in front of it, `first_faces`); a ray's entry is the
//!   nearest front-facing boundary face of its tile;
//! - the walk leaves each tet through the face with the smallest ray parameter ahead and
//!   goes on in the face neighbour; the scalar is linear inside a tet (a gradient per tet);
//! - each tet's segment is one lookup in the 3D pre-integrated table on (front scalar, back
//!   scalar, length) ([`SegmentTable`]), or point samples when pre-integration is off;
//! - the air around the tissue is cut out once, at creation (`cut_outer_air`): tets whose
//!   node scalars are all invisible (showing a source: that read only invisible values)
//!   and that reach the mesh's surface through such tets are not walked, so rays enter
//!   where the tissue starts;
//! - a ray that leaves a non-convex mesh looks for its next boundary hit and re-enters
//!   (from a tolerance behind where it left: through an edge, the next tet starts there);
//! - a ray that starts inside the mesh (the camera in the organ) meets an exit face first:
//!   it walks back from there to the tet holding its origin and starts there;
//! - a tool hit ends the ray: the tool is what lies behind the tissue in front of it;
//! - the tets are kept in a spatial order (`order.rs`), whatever order the mesh lists them
//!   in, so a ray's next tet is usually near in memory;
//! - pre-integrated node scalars on a CPU with AVX2 walk eight rays side by side
//!   (`lanes.rs`), the same bits: a strip of tiles' rays share the lanes, each ray's
//!   entries and re-entries (`next_start`, `walked_to`) the one-ray code's.
//!
//! Face planes and gradients are refreshed with [`TetRaycaster::update`] after every
//! deformation step. Geometry is kept in f32 relative to the rest mesh's centre (`anchor`),
//! as the GPU holds it. [`reference()`] is the independent f64 integral the tests use.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::entry::{Search, TileFaces};
use super::field::V3;
use super::geometry::{tet_geometry, tet_geometry_8, tet_geometry_f32, TetGeometry};
use super::look::SourceLook;
use super::order::{renumbered_neighbours, spatial_order};
use crate::camera::{Camera, Projection, Rays};
use crate::transfer::{SegmentTable, Tables, TransferFunction};
use crate::volume::{nearest_tool, ToolPicture, MAX_TOOLS};
use crate::{RenderError, Rendered};
use defvol_core::mesh::{TetMesh, TET_FACES};

#[derive(Debug, Clone, PartialEq)]
pub struct TetRaycastParams {
    /// Pre-integrated: the longest piece a segment is looked up in (the table's length
    /// range; longer segments are split). Point-sampled: the sub-step. World units.
    pub step: f64,
    pub preintegrated: bool,
    pub early_termination: f64,
    pub background: [f64; 4],
    /// Tools drawn into the picture, opaque, at their depth (up to [`MAX_TOOLS`]).
    pub tools: Vec<ToolPicture>,
    /// Ambient share of the tools' headlight shading.
    pub ambient: f64,
}

impl Default for TetRaycastParams {
    fn default() -> Self {
        Self {
            step: 4.0,
            preintegrated: true,
            early_termination: 0.999,
            background: [0.0, 0.0, 0.0, 1.0],
            tools: Vec::new(),
            ambient: 0.35,
        }
    }
}

/// Side of the square pixel tiles boundary faces are binned into (the GPU's workgroup).
pub const TILE: usize = 8;
/// Entry face of a walk that starts inside a tet (the camera in the mesh).
pub(crate) const NO_FACE: u32 = 4;
/// The most boundary crossings into the mesh one ray follows.
pub(crate) const MAX_ENTRIES: usize = 64;
/// The most tets one walk crosses.
pub(crate) const MAX_WALK: usize = 1 << 16;
/// Longest run of zero-length segments before a walk is abandoned: a ray through an edge
/// or a vertex can circle the tets around it without moving on.
pub(crate) const MAX_STALL: u32 = 64;
/// The most pieces a long segment is split into.
pub(crate) const MAX_PIECES: usize = 4096;
/// The most tets the eight-lane walk takes: its gathers index the geometry's floats in i32
/// (larger meshes, over 100M tets, walk one ray at a time).
#[cfg(target_arch = "x86_64")]
pub(crate) const LANES_MAX_TETS: usize = i32::MAX as usize / (std::mem::size_of::<TetGeometry>() / 4);

/// Steps the pre-integrated table's lengths reach: a segment through a tet is one lookup
/// where it can be (segments through a fine mesh are longer than a step: fewer lookups,
/// the same PSNR; see docs/perf/journal.md#pre-integrated-segment-lengths), its length
/// levels still an eighth of a step apart.
const TABLE_STEPS: f64 = 4.0;

/// Per tet and face: the neighbour across it as tet · 4 + its face, or -1.
fn face_links(neighbours: &[[i32; 4]]) -> Vec<[i32; 4]> {
    neighbours
        .iter()
        .enumerate()
        .map(|(t, n)| {
            n.map(|m| match usize::try_from(m) {
                Ok(m) => neighbours[m].iter().position(|&b| b == t as i32).map_or(-1, |face| (m * 4 + face) as i32),
                Err(_) => -1,
            })
        })
        .collect()
}

/// The mesh's tets in the order the walk keeps them ([`spatial_order`]: new index → the
/// mesh's index), the tets in that order and their face links.
fn ordered(mesh: &TetMesh) -> (Vec<usize>, Vec<[u32; 4]>, Vec<[i32; 4]>) {
    let order = spatial_order(mesh);
    let tets = order.iter().map(|&t| mesh.tets()[t]).collect();
    let links = face_links(&renumbered_neighbours(mesh.neighbours(), &order));
    (order, tets, links)
}

/// The faces of walked tets with no neighbour, as tet · 4 + face (`links` or the mesh's
/// neighbours: a negative entry is no neighbour in both).
fn boundary_faces(links: &[[i32; 4]], walked: &[bool]) -> Vec<u32> {
    links
        .iter()
        .zip(walked)
        .enumerate()
        .filter(|(_, (_, &w))| w)
        .flat_map(|(t, (n, _))| (0..4u32).filter(move |&k| n[k as usize] < 0).map(move |k| t as u32 * 4 + k))
        .collect()
}

/// Which tets rays walk: all but the air around the tissue, the tets that are `invisible`
/// (node scalars all outside the visible span, or a source's tet that reads only invisible
/// values) and that reach the mesh's surface through such tets. They contribute nothing (a
/// source: its samples' grid then starts at the tissue, as accurate), so the mesh is
/// rendered without them (their links cut): a ray enters where visible tissue starts
/// instead of walking from the mesh's bounding surface through the air (a lattice over a
/// scan is mostly air around the body). Invisible pockets inside the tissue stay walked:
/// cut out, each would be another surface to find and re-enter through.
fn cut_outer_air(links: &mut [[i32; 4]], invisible: impl Fn(usize) -> bool) -> Vec<bool> {
    let mut walked = vec![true; links.len()];
    let mut stack: Vec<usize> = (0..links.len()).filter(|&t| links[t].iter().any(|&l| l < 0) && invisible(t)).collect();
    for &t in &stack {
        walked[t] = false;
    }
    while let Some(t) = stack.pop() {
        for &link in &links[t] {
            let Ok(next) = usize::try_from(link >> 2) else { continue };
            if walked[next] && invisible(next) {
                walked[next] = false;
                stack.push(next);
            }
        }
    }
    for (t, tet_links) in links.iter_mut().enumerate() {
        for link in tet_links.iter_mut() {
            if !walked[t] || usize::try_from(*link >> 2).is_ok_and(|next| !walked[next]) {
                *link = -1;
            }
        }
    }
    walked
}

/// Boundary faces (tet · 4 + face) binned into the image's tiles: tile t holds
/// `faces[start[t]..start[t + 1]]`.
#[derive(Debug, Clone)]
pub(crate) struct Bins {
    pub(crate) tiles: [usize; 2],
    pub(crate) start: Vec<u32>,
    pub(crate) faces: Vec<u32>,
}

impl Bins {
    pub(crate) fn tile(&self, px: usize, py: usize) -> &[u32] {
        let t = (py / TILE) * self.tiles[0] + px / TILE;
        &self.faces[self.start[t] as usize..self.start[t + 1] as usize]
    }
}

/// Bins each boundary face into the tiles its projected box covers. A face wholly behind
/// the camera is dropped (rays only go forward); one crossing the eye's plane covers every
/// tile.
pub(crate) fn bin_boundary(tets: &[[u32; 4]], boundary: &[u32], positions: &[Vector3<f64>], camera: &Camera) -> Bins {
    let (w, h) = (camera.width, camera.height);
    let tiles = [w.div_ceil(TILE), h.div_ceil(TILE)];
    let camera_from_world = camera.world_from_camera.inverse();
    let aspect = w as f64 / h as f64;
    let tile_box = |face: u32| -> Option<[usize; 4]> {
        let nodes = tets[(face >> 2) as usize];
        let corners =
            TET_FACES[(face & 3) as usize].map(|i| camera_from_world * Point3::from(positions[nodes[i] as usize]));
        if corners.iter().all(|c| c.z <= 0.0) {
            return None;
        }
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for c in &corners {
            let (u, v) = match camera.projection {
                Projection::Perspective { fov_y_deg } => {
                    if c.z <= 1e-9 {
                        return Some([0, tiles[0] - 1, 0, tiles[1] - 1]);
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
        // One pixel of margin: the hit test has a tolerance, the box must not be tighter.
        if hi[0] < -1.0 || hi[1] < -1.0 || lo[0] > w as f64 || lo[1] > h as f64 {
            return None;
        }
        let tile = |v: f64, n: usize| ((v.max(0.0) as usize) / TILE).min(n - 1);
        Some([
            tile(lo[0] - 1.0, tiles[0]),
            tile(hi[0] + 1.0, tiles[0]),
            tile(lo[1] - 1.0, tiles[1]),
            tile(hi[1] + 1.0, tiles[1]),
        ])
    };
    let boxes: Vec<(u32, [usize; 4])> = boundary.par_iter().filter_map(|&f| tile_box(f).map(|b| (f, b))).collect();
    let mut count = vec![0u32; tiles[0] * tiles[1] + 1];
    for (_, [x0, x1, y0, y1]) in &boxes {
        for ty in *y0..=*y1 {
            for c in &mut count[ty * tiles[0] + x0..=ty * tiles[0] + x1] {
                *c += 1;
            }
        }
    }
    let mut start = Vec::with_capacity(count.len());
    let mut total = 0u32;
    for c in &count {
        start.push(total);
        total += c;
    }
    let mut fill = start.clone();
    let mut faces = vec![0u32; total as usize];
    for (f, [x0, x1, y0, y1]) in &boxes {
        for ty in *y0..=*y1 {
            for tx in *x0..=*x1 {
                let slot = &mut fill[ty * tiles[0] + tx];
                faces[*slot as usize] = *f;
                *slot += 1;
            }
        }
    }
    Bins { tiles, start, faces }
}

#[inline]
fn plane_t(plane: &[f32; 4], o: &V3, d: &V3) -> (f32, f32) {
    let denom = plane[0] * d.x + plane[1] * d.y + plane[2] * d.z;
    (denom, (plane[3] - (plane[0] * o.x + plane[1] * o.y + plane[2] * o.z)) / denom)
}

/// The face a ray `o + d·t` leaves a tet by (planes as in [`TetGeometry`]): of the faces
/// other than `face_in` it moves out through (denominator above 1e-7), the one with the
/// smallest ray parameter, and that parameter; none where no face lies ahead. The four
/// faces at once in SSE lanes, without a branch per face (see
/// docs/perf/journal.md#exit-faces-in-sse-lanes; the shader compares without dividing, as
/// the one-face loop does: the same face but where a ray passes within rounding of an
/// edge).
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "sse2")]
fn exit_face(planes: &[[f32; 4]; 4], o: &V3, d: &V3, face_in: u32) -> Option<(u32, f32)> {
    use std::arch::x86_64::*;
    // SAFETY: each plane holds four floats.
    let rows = planes.map(|p| unsafe { _mm_loadu_ps(p.as_ptr()) });
    // Rows to columns: lane k of x, y, z, w is face k's.
    let (t0, t1) = (_mm_unpacklo_ps(rows[0], rows[1]), _mm_unpacklo_ps(rows[2], rows[3]));
    let (t2, t3) = (_mm_unpackhi_ps(rows[0], rows[1]), _mm_unpackhi_ps(rows[2], rows[3]));
    let (x, y) = (_mm_movelh_ps(t0, t1), _mm_movehl_ps(t1, t0));
    let (z, w) = (_mm_movelh_ps(t2, t3), _mm_movehl_ps(t3, t2));
    let dot = |v: &V3| {
        let term = |c: __m128, v: f32| _mm_mul_ps(c, _mm_set1_ps(v));
        _mm_add_ps(_mm_add_ps(term(x, v.x), term(y, v.y)), term(z, v.z))
    };
    let denom = dot(d);
    // Not the entry face, and ahead (a NaN denominator compares false).
    let entry = _mm_castsi128_ps(_mm_cmpeq_epi32(_mm_setr_epi32(0, 1, 2, 3), _mm_set1_epi32(face_in as i32)));
    let valid = _mm_andnot_ps(entry, _mm_cmpgt_ps(denom, _mm_set1_ps(1e-7)));
    let t = _mm_div_ps(_mm_sub_ps(w, dot(o)), denom);
    let t = _mm_or_ps(_mm_and_ps(valid, t), _mm_andnot_ps(valid, _mm_set1_ps(f32::INFINITY)));
    let m = _mm_min_ps(t, _mm_shuffle_ps::<0b10_11_00_01>(t, t));
    let m = _mm_min_ps(m, _mm_shuffle_ps::<0b01_00_11_10>(m, m));
    // The first face at the minimum, as the loop keeps the first of equals.
    let hits = _mm_movemask_ps(_mm_and_ps(valid, _mm_cmpeq_ps(t, m)));
    (hits != 0).then(|| (hits.trailing_zeros(), _mm_cvtss_f32(m)))
}

/// `t_exit` no earlier than `t_in` and no later than `t_stop`, by plain comparisons: the
/// walk's values are never NaN, so `f32::max`/`min`'s NaN handling (a compare and a blend
/// each) only lengthened every step (see docs/perf/journal.md#plain-comparisons-in-the-walk).
#[inline(always)]
fn ahead(t_exit: f32, t_in: f32, t_stop: f32) -> f32 {
    let t = if t_exit > t_in { t_exit } else { t_in };
    if t < t_stop {
        t
    } else {
        t_stop
    }
}

/// Whether a segment whose scalar runs from `s.0` to `s.1` reaches into the open interval
/// `visible`: `max(s) > lo && min(s) < hi` in comparisons without `f32::max`/`min`'s NaN
/// handling (the same answer, a NaN comparing false in both).
#[inline(always)]
fn seen(s: (f32, f32), (lo, hi): (f32, f32)) -> bool {
    (s.0 > lo || s.1 > lo) & (s.0 < hi || s.1 < hi)
}

/// [`exit_face`] one face at a time, comparing num/denom without dividing (elsewhere than
/// x86-64, and its twin in the tests).
#[cfg(any(test, not(target_arch = "x86_64")))]
fn exit_face_scalar(planes: &[[f32; 4]; 4], o: &V3, d: &V3, face_in: u32) -> Option<(u32, f32)> {
    let (mut num, mut den) = (0.0f32, 0.0f32);
    let mut exit_k = NO_FACE;
    for (k, plane) in planes.iter().enumerate() {
        let denom = plane[0] * d.x + plane[1] * d.y + plane[2] * d.z;
        if k as u32 == face_in || denom <= 1e-7 || denom.is_nan() {
            continue;
        }
        let n = plane[3] - (plane[0] * o.x + plane[1] * o.y + plane[2] * o.z);
        if exit_k == NO_FACE || n * den < num * denom {
            (num, den, exit_k) = (n, denom, k as u32);
        }
    }
    (exit_k != NO_FACE).then(|| (exit_k, num / den))
}

/// A mesh prepared for rendering: it owns what it needs, so a frame worker can keep one.
pub struct TetRaycaster {
    tets: Vec<[u32; 4]>,
    scalars: Vec<f32>,
    pub(crate) positions: Vec<Vector3<f64>>,
    pub(crate) anchor: Vector3<f64>,
    pub(crate) geometry: Vec<TetGeometry>,
    /// Per tet and face: the neighbour across it as tet · 4 + its face, or -1.
    pub(crate) links: Vec<[i32; 4]>,
    /// Boundary faces as tet · 4 + face.
    pub(crate) boundary: Vec<u32>,
    /// Per tet: rays walk it (false: the air cut out around the tissue, `cut_outer_air`).
    walked: Vec<bool>,
    pub(crate) table: SegmentTable,
    pub(crate) tables: Tables,
    /// How far outside a face's triangle a hit still counts (world units).
    pub(crate) tolerance: f32,
    /// Scalars outside this open interval are transparent ([`TransferFunction::visible_span`]).
    pub(crate) visible: (f32, f32),
    pub(crate) params: TetRaycastParams,
    /// Showing the source volume through the mesh instead of node scalars.
    pub(crate) source: Option<Box<SourceLook>>,
}

impl TetRaycaster {
    /// `scalars`: one value per node (the values the transfer function maps).
    pub fn new(
        mesh: &TetMesh,
        scalars: &[f32],
        tf: &TransferFunction,
        params: &TetRaycastParams,
    ) -> Result<Self, RenderError> {
        Self::prepare(mesh, scalars, tf, params, None)
    }

    pub(crate) fn prepare(
        mesh: &TetMesh,
        scalars: &[f32],
        tf: &TransferFunction,
        params: &TetRaycastParams,
        mut source: Option<Box<SourceLook>>,
    ) -> Result<Self, RenderError> {
        if scalars.len() != mesh.nodes().len() || scalars.iter().any(|s| !s.is_finite()) {
            return Err(RenderError::Parameter(format!(
                "{} scalars for {} nodes (all must be finite)",
                scalars.len(),
                mesh.nodes().len()
            )));
        }
        if !(params.step.is_finite() && params.step > 0.0) {
            return Err(RenderError::Parameter(format!("step {} must be finite and > 0", params.step)));
        }
        if !(params.early_termination.is_finite() && params.early_termination > 0.0 && params.early_termination <= 1.0)
        {
            return Err(RenderError::Parameter(format!(
                "early termination {} must be in (0, 1]",
                params.early_termination
            )));
        }
        if params.tools.len() > MAX_TOOLS {
            return Err(RenderError::Parameter(format!(
                "{} tools; a picture draws up to {MAX_TOOLS}",
                params.tools.len()
            )));
        }
        for tool in &params.tools {
            tool.validate()?;
        }
        let range = scalars.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), s| (lo.min(*s), hi.max(*s)));
        let tf = tf.resolve(range)?;
        let far = |v: f64| v.clamp(-1e30, 1e30) as f32;
        let visible = tf.visible_span();
        let visible = (far(visible.0), far(visible.1));
        let (order, tets, mut links) = ordered(mesh);
        if let Some(source) = &mut source {
            source.visible = order.iter().map(|&t| source.visible[t]).collect();
        }
        let walked = match &source {
            None => cut_outer_air(&mut links, |t| {
                let (lo, hi) = tets[t].iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &i| {
                    (lo.min(scalars[i as usize]), hi.max(scalars[i as usize]))
                });
                hi <= visible.0 || lo >= visible.1
            }),
            // The source's visibility is per tet already, from the values its samples read.
            Some(source) => cut_outer_air(&mut links, |t| source.visible[t] == 0),
        };
        let boundary = boundary_faces(&links, &walked);
        let (lo, hi) = mesh
            .nodes()
            .iter()
            .fold((Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY)), |(lo, hi), p| {
                (lo.inf(p), hi.sup(p))
            });
        let (anchor, diagonal) =
            if mesh.nodes().is_empty() { (Vector3::zeros(), 1.0) } else { ((lo + hi) / 2.0, (hi - lo).norm()) };
        let table = if params.preintegrated {
            SegmentTable::new(&tf, range, params.step * TABLE_STEPS)
        } else {
            SegmentTable { lo: 0.0, hi: 1.0, max_len: 1.0, level_scale: 1.0, length_scale: 1.0, entries: Vec::new() }
        };
        let mut raycaster = Self {
            tets,
            scalars: scalars.to_vec(),
            positions: Vec::new(),
            anchor,
            geometry: Vec::new(),
            links,
            boundary,
            walked,
            table,
            tables: Tables::new(&tf, range, params.step, false),
            tolerance: (1e-5 * diagonal.max(1e-9)) as f32,
            visible,
            params: params.clone(),
            source,
        };
        raycaster.update(mesh.nodes())?;
        Ok(raycaster)
    }

    /// The tets in the raycaster's order (spatial, `order.rs`), not the mesh's.
    pub fn tets(&self) -> &[[u32; 4]] {
        &self.tets
    }

    /// The tools drawn into the next frames (up to [`MAX_TOOLS`]).
    pub fn set_tools(&mut self, tools: Vec<ToolPicture>) -> Result<(), RenderError> {
        if tools.len() > MAX_TOOLS {
            return Err(RenderError::Parameter(format!("{} tools; a picture draws up to {MAX_TOOLS}", tools.len())));
        }
        for tool in &tools {
            tool.validate()?;
        }
        self.params.tools = tools;
        Ok(())
    }

    pub fn scalars(&self) -> &[f32] {
        &self.scalars
    }

    pub fn params(&self) -> &TetRaycastParams {
        &self.params
    }

    /// New node positions (a deformation step): face planes and gradients recomputed.
    pub fn update(&mut self, positions: &[Vector3<f64>]) -> Result<(), RenderError> {
        check_positions(positions, self.scalars.len())?;
        // Written in place: a fresh 12 MB at 155k tets would fault its pages in every frame.
        self.positions.clear();
        self.positions.extend_from_slice(positions);
        let anchored: Vec<V3> = positions.iter().map(|p| (p - self.anchor).cast::<f32>()).collect();
        let (tets, scalars) = (&self.tets, &self.scalars);
        self.geometry.resize(tets.len(), TetGeometry::default());
        // Eight tets at a time. Tets cut out are never read: their geometry is left as it was.
        let chunks = self.geometry.par_chunks_mut(8).zip(tets.par_chunks(8)).zip(self.walked.par_chunks(8));
        chunks.for_each(|((geometry, tets), walked)| {
            let x = |tet: &[u32; 4]| tet.map(|i| anchored[i as usize]);
            let s = |tet: &[u32; 4]| tet.map(|i| scalars[i as usize]);
            match <&[[u32; 4]; 8]>::try_from(tets) {
                Ok(eight) => {
                    let fresh = tet_geometry_8(&eight.map(|t| x(&t)), &eight.map(|t| s(&t)));
                    for ((g, fresh), &walked) in geometry.iter_mut().zip(fresh).zip(walked) {
                        if walked {
                            *g = fresh;
                        }
                    }
                }
                Err(_) => {
                    for ((g, tet), &walked) in geometry.iter_mut().zip(tets).zip(walked) {
                        if walked {
                            *g = tet_geometry_f32(&x(tet), &s(tet));
                        }
                    }
                }
            }
        });
        if let Some(source) = &mut self.source {
            source.update_maps(&self.tets, &anchored);
        }
        Ok(())
    }

    /// One frame seen by `camera`.
    pub fn render(&self, camera: &Camera) -> Result<Rendered, RenderError> {
        camera.validate()?;
        let bins = bin_boundary(&self.tets, &self.first_faces(camera), &self.positions, camera);
        let rays = camera.rays();
        let (w, h) = (camera.width, camera.height);
        let mut rgba = vec![0u8; w * h * 4];
        let mut depth = vec![f32::INFINITY; w * h];
        // A strip of tiles is TILE whole rows of the image.
        let strips = rgba.par_chunks_mut(TILE * w * 4).zip(depth.par_chunks_mut(TILE * w));
        strips.enumerate().for_each(|(row, (rgba, depth))| {
            let first = row * TILE * w;
            for StripRay { pixel, ray, .. } in self.cast_strip_rays(&bins, &rays, row, true) {
                let (color, d) = ray.finish();
                let i = pixel - first;
                rgba[i * 4..i * 4 + 4].copy_from_slice(&color.map(crate::volume::to_level));
                depth[i] = d;
            }
        });
        Ok(Rendered { width: w, height: h, rgba, depth })
    }

    /// Whether rays walk eight at a time ([`super::lanes`]): pre-integrated node scalars on
    /// a CPU with AVX2, in a mesh the lanes' indices reach.
    fn lanes_walk(&self) -> bool {
        #[cfg(target_arch = "x86_64")]
        return self.params.preintegrated
            && self.source.is_none()
            && self.tets.len() <= LANES_MAX_TETS
            && defvol_core::volume::lanes::lanes_available();
        #[cfg(not(target_arch = "x86_64"))]
        false
    }

    /// Whether rays walk eight at a time through the source (`super::source_lanes`): where
    /// its samples allow it (`SourceLook::lanes_serve`), in a mesh the lanes' indices
    /// reach.
    fn source_lanes_walk(&self) -> bool {
        #[cfg(target_arch = "x86_64")]
        return self.source.as_ref().is_some_and(|s| s.lanes_serve()) && self.tets.len() <= LANES_MAX_TETS;
        #[cfg(not(target_arch = "x86_64"))]
        false
    }

    /// The rays of the strip of tiles `row` cast, walked eight at a time where `lanes` asks
    /// it and [`Self::lanes_walk`] or [`Self::source_lanes_walk`] allows it, else one by
    /// one; tile by tile, as the GPU's workgroups: neighbouring rays cross the same tets
    /// while their geometry is in cache.
    fn cast_strip_rays(&self, bins: &Bins, rays: &Rays, row: usize, lanes: bool) -> Vec<StripRay> {
        let source_lanes = lanes && self.source_lanes_walk();
        let lanes = lanes && self.lanes_walk();
        let (w, h) = (rays.camera.width, rays.camera.height);
        let ty = row * TILE;
        let tiles: Vec<TileFaces> =
            (0..bins.tiles[0]).map(|c| TileFaces::new(bins.tile(c * TILE, ty), &self.geometry)).collect();
        let mut strip = Vec::with_capacity(TILE * w);
        for (tile, tx) in (0..w).step_by(TILE).enumerate() {
            for py in ty..(ty + TILE).min(h) {
                for px in tx..(tx + TILE).min(w) {
                    let (origin, direction) = rays.ray(px, py);
                    strip.push(StripRay { tile, pixel: py * w + px, ray: self.ray(&origin, &direction) });
                }
            }
        }
        #[cfg(target_arch = "x86_64")]
        if lanes {
            // SAFETY: `lanes_walk` checked AVX2, pre-integration, no source and the mesh's size.
            unsafe { self.cast_strip(&tiles, &mut strip) };
            return strip;
        }
        // SAFETY: `source_lanes_walk` checked AVX2 (the source's sampler) and the mesh's size.
        #[cfg(target_arch = "x86_64")]
        if source_lanes && unsafe { self.cast_source_strip(&tiles, &mut strip) } {
            return strip;
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (lanes, source_lanes);
        for StripRay { tile, ray, .. } in &mut strip {
            self.cast(&tiles[*tile], ray);
        }
        strip
    }

    /// The ray from `origin` along unit `direction`, ended by the nearest tool it meets.
    fn ray(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> Ray {
        let tool = nearest_tool(&self.params.tools, self.params.ambient, origin, direction, &-direction);
        let (behind, t_stop) = match tool {
            Some((t, color)) => (color, t),
            None => (self.params.background.map(|c| c as f32), f32::INFINITY),
        };
        Ray {
            o: (origin.coords - self.anchor).cast::<f32>(),
            d: direction.cast::<f32>(),
            t_stop,
            behind,
            acc: [0.0; 4],
            depth: f32::INFINITY,
            t_from: 0.0,
            walked: false,
            last_start: f32::NEG_INFINITY,
            fronts_until: f32::NEG_INFINITY,
            entries: 0,
        }
    }

    /// The boundary faces a ray of `camera` can meet: all of them when a ray may start
    /// inside the mesh; else (the mesh wholly in front of the eye's plane) only those facing
    /// the rays, about half, since a ray from outside enters the mesh before it leaves it
    /// and, once walked, looks for entries only.
    fn first_faces(&self, camera: &Camera) -> Vec<u32> {
        let camera_from_world = camera.world_from_camera.inverse();
        let tets = &self.tets;
        let in_front = self.boundary.par_iter().all(|&f| {
            let nodes = tets[(f >> 2) as usize];
            TET_FACES[(f & 3) as usize]
                .iter()
                .all(|&i| (camera_from_world * Point3::from(self.positions[nodes[i] as usize])).z > 0.0)
        });
        if !in_front {
            return self.boundary.clone();
        }
        let (origin, direction) = camera.ray(0, 0);
        let (o, d) = ((origin.coords - self.anchor).cast::<f32>(), direction.cast::<f32>());
        let perspective = matches!(camera.projection, Projection::Perspective { .. });
        self.boundary
            .par_iter()
            .copied()
            .filter(|&f| {
                let plane = &self.geometry[(f >> 2) as usize].planes[(f & 3) as usize];
                if perspective {
                    // The eye strictly inside the face's plane: every ray from it crosses
                    // the plane going out.
                    plane[3] - (plane[0] * o.x + plane[1] * o.y + plane[2] * o.z) <= 0.0
                } else {
                    plane_t(plane, &o, &d).0 <= 0.0
                }
            })
            .collect()
    }

    /// One ray to its end, walk after walk: what it gathers in `ray.acc` and `ray.depth`.
    fn cast(&self, faces: &TileFaces, ray: &mut Ray) {
        while let Some(start) = self.next_start(faces, ray) {
            let t = self.walk(start, &ray.o, &ray.d, ray.t_stop, &mut ray.acc, &mut ray.depth);
            if !self.walked_to(ray, t) {
                break;
            }
        }
    }

    /// Where the ray's next walk starts (tet, entry face, t), or none: it does not enter
    /// the mesh (again) before its end.
    pub(crate) fn next_start(&self, faces: &TileFaces, ray: &mut Ray) -> Option<(u32, u32, f32)> {
        if ray.entries == MAX_ENTRIES {
            return None;
        }
        ray.entries += 1;
        // Once walked, only entries count, from a tolerance behind where the walk left
        // (a ray leaving through an edge or a vertex enters the next tet there) but past
        // where the last walk started, so every walk starts further on.
        let after = if ray.walked { (ray.t_from - self.tolerance).max(ray.last_start) } else { ray.t_from };
        let search = Search { o: &ray.o, d: &ray.d, after, fronts_only: ray.walked, tolerance: self.tolerance };
        let (hit, fronts_until) = faces.nearest_hit(search);
        let hit = hit.filter(|hit| hit.t < ray.t_stop)?;
        let start = if hit.front {
            (hit.tet, hit.face, hit.t)
        } else {
            // The first boundary ahead is an exit: the ray starts inside the mesh.
            self.locate_back(hit.tet, &ray.o, &ray.d, ray.t_from)
        };
        ray.walked = true;
        ray.last_start = start.2;
        ray.fronts_until = fronts_until;
        Some(start)
    }

    /// The strip's next ray from `*next` on that enters the mesh (`rays[k]`) and where its
    /// walk starts; those passed over are finished as they are.
    pub(crate) fn next_entering(
        &self,
        tiles: &[TileFaces],
        rays: &mut [StripRay],
        next: &mut usize,
    ) -> Option<(usize, (u32, u32, f32))> {
        while *next < rays.len() {
            let k = *next;
            *next += 1;
            let StripRay { tile, ray, .. } = &mut rays[k];
            if let Some(start) = self.next_start(&tiles[*tile], ray) {
                return Some((k, start));
            }
        }
        None
    }

    /// A walk stopped at `t`: whether the ray may enter the mesh again.
    pub(crate) fn walked_to(&self, ray: &mut Ray, t: f32) -> bool {
        ray.t_from = t;
        // Beyond the last front face's plane ahead, the ray cannot enter the mesh again.
        !(ray.acc[3] >= self.params.early_termination as f32
            || t >= ray.t_stop
            || t - self.tolerance >= ray.fronts_until)
    }

    /// From the tet behind an exit face, back along the ray to the tet holding the point at
    /// `t_from`: (tet, the face the ray came in through, t_from).
    fn locate_back(&self, tet: u32, o: &V3, d: &V3, t_from: f32) -> (u32, u32, f32) {
        let mut tet = tet;
        for _ in 0..MAX_WALK {
            let planes = &self.geometry[tet as usize].planes;
            let mut entry_t = f32::NEG_INFINITY;
            let mut entry_k = NO_FACE;
            for (k, plane) in planes.iter().enumerate() {
                let (denom, t) = plane_t(plane, o, d);
                if denom < -1e-7 && t > entry_t {
                    entry_t = t;
                    entry_k = k as u32;
                }
            }
            if entry_k == NO_FACE || entry_t <= t_from {
                return (tet, entry_k, t_from);
            }
            let link = self.links[tet as usize][entry_k as usize];
            if link < 0 {
                return (tet, entry_k, entry_t);
            }
            tet = (link >> 2) as u32;
        }
        (tet, NO_FACE, t_from)
    }

    /// Walks from `start` (tet, entry face, t) through face neighbours until the ray
    /// leaves the mesh, reaches `t_stop` or is opaque: where it stopped.
    fn walk(&self, start: (u32, u32, f32), o: &V3, d: &V3, t_stop: f32, acc: &mut [f32; 4], depth: &mut f32) -> f32 {
        let mut pending = Pending::default();
        let t = self.walk_steps(start, o, d, t_stop, acc, depth, &mut pending);
        self.composite_pending(&mut pending, acc, depth).unwrap_or(t)
    }

    /// The walk itself; segments the table reaches wait in `pending` (see [`Pending`]).
    #[allow(clippy::too_many_arguments)]
    fn walk_steps(
        &self,
        start: (u32, u32, f32),
        o: &V3,
        d: &V3,
        t_stop: f32,
        acc: &mut [f32; 4],
        depth: &mut f32,
        pending: &mut Pending,
    ) -> f32 {
        let (mut tet, mut face_in, mut t_in) = start;
        let termination = self.params.early_termination as f32;
        let mut stalled = 0;
        // Showing the source: samples on one grid from where the ray came in.
        let mut march = self.source.as_ref().map(|s| s.march(o, d, t_in));
        let scalar =
            |g: &[f32; 4], t: f32| g[0] * (o.x + d.x * t) + g[1] * (o.y + d.y * t) + g[2] * (o.z + d.z * t) + g[3];
        // The scalar is continuous across faces: a tet's entry value is the last exit value.
        let mut s_in = scalar(&self.geometry[tet as usize].gradient, t_in);
        for _ in 0..MAX_WALK {
            self.prefetch_neighbours(tet);
            let g = &self.geometry[tet as usize];
            // SAFETY: SSE2 is part of x86-64.
            #[cfg(target_arch = "x86_64")]
            let exit = unsafe { exit_face(&g.planes, o, d, face_in) };
            #[cfg(not(target_arch = "x86_64"))]
            let exit = exit_face_scalar(&g.planes, o, d, face_in);
            let Some((exit_k, t_exit)) = exit else {
                self.flush(&mut march, acc, depth);
                return t_in;
            };
            let t_out = ahead(t_exit, t_in, t_stop);
            stalled = if t_out - t_in <= 1e-6 * (1.0 + t_in.abs()) { stalled + 1 } else { 0 };
            if stalled > MAX_STALL {
                self.flush(&mut march, acc, depth);
                return t_out;
            }
            let s_out = match (&self.source, &mut march) {
                (Some(source), Some(march)) => {
                    source.cross(march, tet as usize, t_out, acc, depth);
                    s_in
                }
                _ => {
                    let s_out = scalar(&g.gradient, t_out);
                    if seen((s_in, s_out), self.visible) {
                        let len = t_out - t_in;
                        if self.params.preintegrated && len > 0.0 && len <= self.table.max_len {
                            // Most segments: one lookup, queued (the loop's one piece, the same bits).
                            if pending.push(s_in, s_in + (s_out - s_in), len, t_in + 0.5 * len, t_out) {
                                if let Some(t) = self.composite_pending(pending, acc, depth) {
                                    return t;
                                }
                            }
                        } else {
                            // Longer segments (and point samples) come after those queued.
                            if pending.len > 0 {
                                if let Some(t) = self.composite_pending(pending, acc, depth) {
                                    return t;
                                }
                            }
                            self.integrate(acc, depth, t_in, t_out, s_in, s_out);
                        }
                    }
                    s_out
                }
            };
            if acc[3] >= termination {
                return t_out;
            }
            let link = self.links[tet as usize][exit_k as usize];
            if t_out >= t_stop || link < 0 {
                // The ray leaves the mesh or meets a tool: the source's last, shorter segment.
                if let (Some(source), Some(march)) = (&self.source, &mut march) {
                    source.finish(march, tet as usize, t_out, acc, depth);
                }
                return t_out;
            }
            (tet, face_in, t_in, s_in) = ((link >> 2) as u32, (link & 3) as u32, t_out, s_out);
        }
        self.flush(&mut march, acc, depth);
        t_in
    }

    /// The source's samples still queued where a walk stopped inside the mesh (it leaves
    /// it through `SourceLook::finish`, which composites them first).
    #[cold]
    fn flush(&self, march: &mut Option<super::look::March>, acc: &mut [f32; 4], depth: &mut f32) {
        if let (Some(source), Some(march)) = (&self.source, march) {
            source.flush(march, acc, depth);
        }
    }

    /// Asks the cache for the geometry of the tets past `tet`'s faces: the walk goes on
    /// into one of them, and would otherwise wait for its planes at each step (the mesh's
    /// geometry is megabytes, a step a few dozen instructions).
    #[inline(always)]
    fn prefetch_neighbours(&self, tet: u32) {
        #[cfg(target_arch = "x86_64")]
        {
            // Every face's neighbour, the one the ray came from and the missing (-1, just
            // before the array) too: a branch per link cost more than the two spare
            // prefetches (512², 155k tets).
            let base = self.geometry.as_ptr();
            for &link in &self.links[tet as usize] {
                let at = base.wrapping_offset((link >> 2) as isize);
                // SAFETY: a prefetch reads nothing, whatever the address.
                unsafe {
                    use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
                    _mm_prefetch::<_MM_HINT_T0>(at.cast());
                    _mm_prefetch::<_MM_HINT_T0>(at.cast::<i8>().wrapping_add(std::mem::size_of::<TetGeometry>() - 1));
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = tet;
    }

    /// The queued segments' lookups, then their compositing in order: `Some(t_out)` of the
    /// segment that made the ray opaque (the rest are dropped, as the walk would have
    /// stopped there), else `None`. `pending` is left empty.
    fn composite_pending(&self, pending: &mut Pending, acc: &mut [f32; 4], depth: &mut f32) -> Option<f32> {
        let n = std::mem::take(&mut pending.len);
        if n == 0 {
            return None;
        }
        let mut entries = [[0.0f32; 4]; PENDING];
        self.lookups(pending, &mut entries[..n]);
        let termination = self.params.early_termination as f32;
        for (k, e) in entries[..n].iter().enumerate() {
            composite(acc, depth, *e, pending.t_mid[k]);
            if acc[3] >= termination {
                return Some(pending.t_out[k]);
            }
        }
        None
    }

    /// The table's entries of the first `entries.len()` pending segments, eight lanes
    /// wide where the CPU has AVX2 (the same bits).
    fn lookups(&self, pending: &Pending, entries: &mut [[f32; 4]]) {
        #[cfg(target_arch = "x86_64")]
        if defvol_core::volume::lanes::lanes_available() {
            // SAFETY: AVX2 is present; the queue's rows hold whole groups of eight.
            unsafe {
                crate::volume::packet::tet_segments_into(
                    &self.table,
                    &pending.front,
                    &pending.back,
                    &pending.length,
                    entries,
                )
            };
            return;
        }
        for (k, e) in entries.iter_mut().enumerate() {
            *e = self.table.lookup(pending.front[k], pending.back[k], pending.length[k]);
        }
    }

    /// The segment [t0, t1], its scalar linear from s0 to s1, in pieces: table lookups no
    /// longer than the table reaches, or point samples a step apart at the pieces' middles.
    pub(crate) fn integrate(&self, acc: &mut [f32; 4], depth: &mut f32, t0: f32, t1: f32, s0: f32, s1: f32) {
        let len = t1 - t0;
        if len <= 0.0 || len.is_nan() {
            return;
        }
        let step = if self.params.preintegrated { self.table.max_len } else { self.params.step as f32 };
        let n = if len <= step { 1 } else { ((len / step).ceil() as usize).min(MAX_PIECES) };
        let inv_n = 1.0 / n as f32;
        let piece = len * inv_n;
        for m in 0..n {
            let e = if self.params.preintegrated {
                let (f0, f1) = (m as f32 * inv_n, (m + 1) as f32 * inv_n);
                self.table.lookup(s0 + (s1 - s0) * f0, s0 + (s1 - s0) * f1, piece)
            } else {
                let e = self.tables.sample(s0 + (s1 - s0) * ((m as f32 + 0.5) * inv_n));
                let alpha = 1.0 - (-e[3] * piece).exp();
                [e[0] * alpha, e[1] * alpha, e[2] * alpha, alpha]
            };
            composite(acc, depth, e, t0 + (m as f32 + 0.5) * piece);
        }
    }
}

/// Segments a walk queues before their table lookups, so that these run eight lanes wide
/// (their clamps, truncations and indices computed once for eight; the same queue looked up
/// one segment at a time was no faster). A ray that turns opaque wastes at most this many
/// minus one steps.
const PENDING: usize = 16;
// The lanes read whole groups of eight from the queue's rows.
const _: () = assert!(PENDING.is_multiple_of(8));

/// A ray's pre-integrated segments waiting for their lookups: front and back scalar,
/// length, middle (for the depth) and end on the ray.
#[derive(Default)]
struct Pending {
    front: [f32; PENDING],
    back: [f32; PENDING],
    length: [f32; PENDING],
    t_mid: [f32; PENDING],
    t_out: [f32; PENDING],
    len: usize,
}

impl Pending {
    /// Queues a segment; true when the queue is full.
    #[inline(always)]
    fn push(&mut self, front: f32, back: f32, length: f32, t_mid: f32, t_out: f32) -> bool {
        let k = self.len;
        (self.front[k], self.back[k], self.length[k], self.t_mid[k], self.t_out[k]) =
            (front, back, length, t_mid, t_out);
        self.len += 1;
        self.len == PENDING
    }
}

/// A ray of a strip of tiles: its tile (an index into the strip's tiles' faces), its
/// pixel in the image and its state.
pub(crate) struct StripRay {
    pub(crate) tile: usize,
    pub(crate) pixel: usize,
    pub(crate) ray: Ray,
}

/// One ray's way through the mesh, kept between its walks: anchored origin and unit
/// direction, where it ends (a tool, else never) and what lies behind, what it has gathered,
/// and where its entry search stands.
pub(crate) struct Ray {
    pub(crate) o: V3,
    pub(crate) d: V3,
    pub(crate) t_stop: f32,
    behind: [f32; 4],
    pub(crate) acc: [f32; 4],
    pub(crate) depth: f32,
    t_from: f32,
    walked: bool,
    last_start: f32,
    fronts_until: f32,
    entries: usize,
}

impl Ray {
    /// Premultiplied RGBA over what lies behind, and the depth where opacity passed 0.5
    /// (else where the ray ends).
    pub(crate) fn finish(&self) -> ([f32; 4], f32) {
        let (acc, bg) = (self.acc, self.behind);
        let rest = 1.0 - acc[3];
        let color = [
            acc[0] + rest * bg[0] * bg[3],
            acc[1] + rest * bg[1] * bg[3],
            acc[2] + rest * bg[2] * bg[3],
            acc[3] + rest * bg[3],
        ];
        (color, if self.depth.is_finite() { self.depth } else { self.t_stop })
    }
}

/// A piece's premultiplied colour and opacity `e` behind what the ray has gathered; the
/// depth is where opacity first passes 0.5 (the piece's middle, `t_mid`).
#[inline(always)]
fn composite(acc: &mut [f32; 4], depth: &mut f32, e: [f32; 4], t_mid: f32) {
    let weight = 1.0 - acc[3];
    for c in 0..4 {
        acc[c] += weight * e[c];
    }
    if depth.is_infinite() && acc[3] >= 0.5 {
        *depth = t_mid;
    }
}

fn check_positions(positions: &[Vector3<f64>], nodes: usize) -> Result<(), RenderError> {
    if positions.len() != nodes || positions.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(RenderError::Parameter(format!(
            "{} positions for {nodes} nodes (all must be finite)",
            positions.len()
        )));
    }
    Ok(())
}

/// The f64 reference: every boundary face of the ray's tile tested exactly (Möller-Trumbore),
/// the walk in f64, the exact transfer function at the middles of sub-steps no longer than
/// `step`; a ray starting inside the mesh starts in the tet found by testing every tet.
/// Linear RGBA per pixel, rows top to bottom.
pub fn reference(
    mesh: &TetMesh,
    positions: &[Vector3<f64>],
    scalars: &[f32],
    camera: &Camera,
    tf: &TransferFunction,
    params: &TetRaycastParams,
) -> Result<Vec<[f64; 4]>, RenderError> {
    camera.validate()?;
    check_positions(positions, mesh.nodes().len())?;
    if scalars.len() != mesh.nodes().len() || !(params.step.is_finite() && params.step > 0.0) {
        return Err(RenderError::Parameter(format!(
            "{} scalars for {} nodes, step {}",
            scalars.len(),
            mesh.nodes().len(),
            params.step
        )));
    }
    let range = scalars.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), s| (lo.min(*s), hi.max(*s)));
    let tf = tf.resolve(range)?;
    let geometry: Vec<_> = mesh
        .tets()
        .iter()
        .map(|tet| tet_geometry(&tet.map(|i| positions[i as usize]), &tet.map(|i| f64::from(scalars[i as usize]))))
        .collect();
    let step = params.step;
    reference_walk(mesh, positions, camera, params, |tet, o, d, t_in, t_out, acc| {
        let g = &geometry[tet].1;
        let s = |t: f64| g[0] * (o.x + d.x * t) + g[1] * (o.y + d.y * t) + g[2] * (o.z + d.z * t) + g[3];
        let n = ((t_out - t_in) / step).ceil().max(1.0) as usize;
        let ds = (t_out - t_in) / n as f64;
        for m in 0..n {
            let (color, tau) = tf.eval(s(t_in + (m as f64 + 0.5) * ds));
            let alpha = (1.0 - acc[3]) * (1.0 - (-tau * ds).exp());
            for c in 0..3 {
                acc[c] += alpha * color[c];
            }
            acc[3] += alpha;
        }
    })
}

/// The exact walk of the references: every boundary face of the ray's tile tested exactly
/// (Möller-Trumbore), tets crossed in f64, `segment(tet, o, d, t_in, t_out, acc)` adding
/// each tet's part of the ray; tools end rays as in the fast paths.
pub(crate) fn reference_walk(
    mesh: &TetMesh,
    positions: &[Vector3<f64>],
    camera: &Camera,
    params: &TetRaycastParams,
    segment: impl Fn(usize, &Vector3<f64>, &Vector3<f64>, f64, f64, &mut [f64; 4]) + Sync,
) -> Result<Vec<[f64; 4]>, RenderError> {
    camera.validate()?;
    check_positions(positions, mesh.nodes().len())?;
    let geometry: Vec<_> =
        mesh.tets().iter().map(|tet| tet_geometry(&tet.map(|i| positions[i as usize]), &[0.0; 4])).collect();
    let neighbours = mesh.neighbours();
    let boundary = boundary_faces(neighbours, &vec![true; neighbours.len()]);
    let bins = bin_boundary(mesh.tets(), &boundary, positions, camera);
    let containing = |p: &Vector3<f64>| {
        geometry.iter().position(|(planes, _)| {
            planes.iter().all(|q| q[0] * p.x + q[1] * p.y + q[2] * p.z - q[3] <= 1e-9 * (1.0 + q[3].abs()))
                && planes.iter().any(|q| q[0] != 0.0 || q[1] != 0.0 || q[2] != 0.0)
        })
    };
    let eye_tet = matches!(camera.projection, Projection::Perspective { .. })
        .then(|| containing(&camera.world_from_camera.translation.vector))
        .flatten();
    let (w, h) = (camera.width, camera.height);
    Ok((0..w * h)
        .into_par_iter()
        .map(|i| {
            let (px, py) = (i % w, i / w);
            let (origin, d) = camera.ray(px, py);
            let o = origin.coords;
            let tool = nearest_tool(&params.tools, params.ambient, &origin, &d, &-d);
            let (bg, t_stop) = match tool {
                Some((t, c)) => (c.map(f64::from), f64::from(t)),
                None => (params.background, f64::INFINITY),
            };
            let mut hits: Vec<(f64, u32, bool)> = bins
                .tile(px, py)
                .iter()
                .filter_map(|&f| {
                    let nodes = mesh.tets()[(f >> 2) as usize];
                    let corners = TET_FACES[(f & 3) as usize].map(|k| positions[nodes[k] as usize]);
                    let plane = geometry[(f >> 2) as usize].0[(f & 3) as usize];
                    ray_triangle(&o, &d, &corners)
                        .map(|t| (t, f, Vector3::new(plane[0], plane[1], plane[2]).dot(&d) < 0.0))
                })
                .collect();
            hits.sort_by(|a, b| a.0.total_cmp(&b.0));
            let mut starts: Vec<(usize, Option<usize>, f64)> =
                hits.iter().filter(|h| h.2).map(|h| ((h.1 >> 2) as usize, Some((h.1 & 3) as usize), h.0)).collect();
            if hits.first().is_some_and(|h| !h.2) {
                if let Some(tet) =
                    if matches!(camera.projection, Projection::Perspective { .. }) { eye_tet } else { containing(&o) }
                {
                    starts.insert(0, (tet, None, 0.0));
                }
            }
            let mut acc = [0.0f64; 4];
            let mut left_at = f64::NEG_INFINITY;
            'entries: for (tet0, face0, t0) in starts {
                if t0 < left_at - 1e-9 || t0 >= t_stop {
                    continue;
                }
                let (mut tet, mut face_in, mut t_in) = (tet0, face0, t0);
                let mut stalled = 0;
                for _ in 0..MAX_WALK {
                    let (planes, _) = &geometry[tet];
                    let exit = (0..4)
                        .filter(|&k| Some(k) != face_in)
                        .filter_map(|k| {
                            let q = planes[k];
                            let denom = q[0] * d.x + q[1] * d.y + q[2] * d.z;
                            (denom > 1e-12).then(|| ((q[3] - (q[0] * o.x + q[1] * o.y + q[2] * o.z)) / denom, k))
                        })
                        .min_by(|a, b| a.0.total_cmp(&b.0));
                    let Some((t_exit, k_exit)) = exit else { break };
                    let t_out = t_exit.max(t_in).min(t_stop);
                    stalled = if t_out - t_in <= 1e-9 * (1.0 + t_in.abs()) { stalled + 1 } else { 0 };
                    if stalled > MAX_STALL {
                        left_at = t_out;
                        break;
                    }
                    segment(tet, &o, &d, t_in, t_out, &mut acc);
                    left_at = t_out;
                    if t_out >= t_stop {
                        break 'entries;
                    }
                    let next = neighbours[tet][k_exit];
                    let Ok(next) = usize::try_from(next) else { break };
                    let Some(back) = neighbours[next].iter().position(|&b| b == tet as i32) else { break };
                    (tet, face_in, t_in) = (next, Some(back), t_out);
                }
            }
            let rest = 1.0 - acc[3];
            [
                acc[0] + rest * bg[0] * bg[3],
                acc[1] + rest * bg[1] * bg[3],
                acc[2] + rest * bg[2] * bg[3],
                acc[3] + rest * bg[3],
            ]
        })
        .collect())
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::source::SourceSampling;
    use crate::transfer::TfPoint;
    use crate::volume::{RaycastParams, Shading};
    use defvol_core::mesh::generate::{lattice, CellSplit};
    use defvol_core::volume::Volume;
    use nalgebra::Matrix3;
    use std::sync::Arc;

    const AIR: f32 = -1000.0;

    /// A camera at `eye` from the centre of [`ball_in_air`]'s lattice, looking at it.
    fn onto_ball(eye: Vector3<f64>, projection: Projection, [width, height]: [usize; 2]) -> Camera {
        let centre = Point3::from(Vector3::repeat(14.0));
        Camera::look_at(centre + eye, centre, Vector3::z(), projection, width, height).unwrap()
    }

    /// A ball of tissue with a bumpy surface and a pocket of air at its centre, in the air
    /// of a 14³-cell lattice (2 mm cells).
    fn ball_in_air() -> (TetMesh, Vec<f32>) {
        let mesh = lattice(Vector3::zeros(), Vector3::repeat(28.0), [14; 3], CellSplit::Five).unwrap();
        let centre = Vector3::repeat(14.0);
        let scalars = mesh
            .nodes()
            .iter()
            .map(|p| {
                let r = (p - centre).norm();
                let bump = 2.0 * (0.7 * p.x).sin() * (0.5 * p.y).cos();
                if r < 3.0 || r > 9.0 + bump {
                    AIR
                } else {
                    (100.0 + 60.0 * (0.4 * p.z).sin()) as f32
                }
            })
            .collect();
        (mesh, scalars)
    }

    fn tissue() -> TransferFunction {
        TransferFunction {
            points: vec![
                TfPoint { value: 0.0, color: [0.2, 0.3, 0.9], opacity: 0.0 },
                TfPoint { value: 100.0, color: [1.0, 0.6, 0.2], opacity: 0.15 },
                TfPoint { value: 200.0, color: [1.0, 1.0, 1.0], opacity: 0.05 },
            ],
            relative: false,
        }
    }

    /// The walk's eight-lane table lookups give `SegmentTable::lookup`'s bits: inside the
    /// table, on and past its scalar range and lengths (clamped), at zero length and for a
    /// NaN scalar (the first level, as the scalar clamps take it).
    #[test]
    fn the_lanes_lookups_give_the_scalar_lookups_bits() {
        if !defvol_core::volume::lanes::lanes_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let table = SegmentTable::new(&tissue(), (-20.0, 230.0), 4.0);
        let mut pending = Pending::default();
        let mut checked = 0;
        for round in 0..64 {
            for k in 0..PENDING {
                let u = (round * PENDING + k) as f32;
                let front = -40.0 + (u * 0.618_034).fract() * 290.0;
                let back = match k {
                    3 => f32::NAN,
                    5 => front,
                    _ => -40.0 + (u * 0.414_214).fract() * 290.0,
                };
                let length = if k == 7 { 0.0 } else { (u * 0.732_051).fract() * 4.6 };
                pending.push(front, back, length, 0.0, 0.0);
            }
            let mut lanes = [[0.0f32; 4]; PENDING];
            // SAFETY: AVX2 is present; the rows hold whole groups of eight.
            unsafe {
                crate::volume::packet::tet_segments_into(
                    &table,
                    &pending.front,
                    &pending.back,
                    &pending.length,
                    &mut lanes,
                )
            };
            for (k, got) in lanes.iter().enumerate() {
                let want = table.lookup(pending.front[k], pending.back[k], pending.length[k]);
                assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits), "segment {k} of round {round}");
                checked += usize::from(want[3] > 0.0);
            }
            pending.len = 0;
        }
        assert!(checked > 500, "only {checked} segments with opacity");
    }

    /// The walk's clamp and visibility test by plain comparisons give what `f32::max` and
    /// `min` give, over random values, equal ones, signed zeros, infinities and (for the
    /// visibility test, whose scalars may be anything the volume holds) NaN.
    #[test]
    fn the_plain_comparisons_give_max_and_mins_answers() {
        let mut rng = fastrand::Rng::with_seed(7);
        let special = [0.0, -0.0, 1.0, -1.0, f32::INFINITY, f32::NEG_INFINITY, f32::MAX, f32::MIN_POSITIVE];
        let mut value = |nan: bool| match rng.u32(0..10) {
            0 => special[rng.usize(..special.len())],
            1 if nan => f32::NAN,
            _ => (rng.f32() * 2.0 - 1.0) * 100.0,
        };
        let (mut clamped, mut shown, mut hidden) = (0, 0, 0);
        for _ in 0..200_000 {
            let (t_exit, t_in, t_stop) = (value(false), value(false), value(false));
            let want = t_exit.max(t_in).min(t_stop);
            assert!(ahead(t_exit, t_in, t_stop) == want, "{t_exit} {t_in} {t_stop}");
            clamped += usize::from(want != t_exit);
            let (s, lo, hi) = ((value(true), value(true)), value(false), value(false));
            let want = s.0.max(s.1) > lo && s.0.min(s.1) < hi;
            assert_eq!(seen(s, (lo, hi)), want, "{s:?} against ({lo}, {hi})");
            (shown, hidden) = if want { (shown + 1, hidden) } else { (shown, hidden + 1) };
        }
        assert!(clamped > 50_000 && shown > 20_000 && hidden > 20_000, "{clamped} {shown} {hidden}");
    }

    /// The four faces in SSE lanes pick the exit face and parameter the one-face loop
    /// picks (bit for bit; where a ray passes within rounding of an edge, either face of
    /// it), and the parameter is the f64 plane intersection's, over random tets and rays
    /// and every entry face.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_lanes_exit_face_is_the_loops_and_the_f64_exit() {
        let mut rng = fastrand::Rng::with_seed(38);
        let mut next = move || rng.f64() * 2.0 - 1.0;
        let (mut same, mut ties, mut none) = (0, 0, 0);
        for round in 0..4000 {
            let x: [Vector3<f64>; 4] = std::array::from_fn(|_| Vector3::new(next(), next(), next()) * 10.0);
            let (planes64, _) = tet_geometry(&x, &[0.0; 4]);
            let planes = planes64.map(|p| p.map(|c| c as f32));
            let o64 = Vector3::new(next(), next(), next()) * 30.0;
            let d64 = Vector3::new(next(), next(), next()).normalize();
            let (o, d) = (o64.cast::<f32>(), d64.cast::<f32>());
            for face_in in 0..=NO_FACE {
                // SAFETY: SSE2 is part of x86-64.
                let lanes = unsafe { exit_face(&planes, &o, &d, face_in) };
                let looped = exit_face_scalar(&planes, &o, &d, face_in);
                let (Some((k, t)), Some((k_loop, t_loop))) = (lanes, looped) else {
                    assert_eq!(lanes.is_none(), looped.is_none(), "round {round}, face {face_in}");
                    none += 1;
                    continue;
                };
                if k == k_loop {
                    assert_eq!(t.to_bits(), t_loop.to_bits(), "round {round}, face {face_in}");
                    same += 1;
                } else {
                    assert!((t - t_loop).abs() <= 1e-5 * (1.0 + t.abs()), "round {round}: {t} against {t_loop}");
                    ties += 1;
                }
                let p = &planes64[k as usize];
                let want =
                    (p[3] - p[0] * o64.x - p[1] * o64.y - p[2] * o64.z) / (p[0] * d64.x + p[1] * d64.y + p[2] * d64.z);
                assert!(
                    (f64::from(t) - want).abs() <= 1e-3 * (1.0 + want.abs()),
                    "round {round}: {t} against f64 {want}"
                );
            }
        }
        assert!(same > 15_000 && none > 100 && ties < 20, "{same} same, {ties} ties, {none} without an exit");
    }

    fn invisible(tet: &[u32; 4], scalars: &[f32]) -> bool {
        tet.iter().all(|&i| scalars[i as usize] <= 0.0)
    }

    #[test]
    fn the_air_around_the_tissue_is_cut_and_pockets_inside_are_kept() {
        let (mesh, scalars) = ball_in_air();
        let raycaster = TetRaycaster::new(&mesh, &scalars, &tissue(), &TetRaycastParams::default()).unwrap();
        // In the raycaster's order of the tets.
        let full = ordered(&mesh).2;
        let cut: Vec<bool> = raycaster.walked.iter().map(|w| !w).collect();
        let centre = Vector3::repeat(14.0);
        let mut pocket = 0;
        for (t, tet) in raycaster.tets.iter().enumerate() {
            let mid = tet.iter().map(|&i| mesh.nodes()[i as usize]).sum::<Vector3<f64>>() / 4.0;
            if cut[t] {
                assert!(invisible(tet, &scalars), "tet {t} is cut but has visible scalars");
            } else if invisible(tet, &scalars) {
                // Kept although invisible: it must not touch the cut air (else it is air too).
                assert!(
                    full[t].iter().all(|&l| l < 0 || !cut[(l >> 2) as usize]),
                    "invisible tet {t} touches the cut air but is kept"
                );
                assert!(full[t].iter().all(|&l| l >= 0), "invisible tet {t} on the mesh's surface is kept");
            }
            if (mid - centre).norm() < 2.0 {
                assert!(!cut[t], "tet {t} of the pocket inside the tissue is cut");
                pocket += 1;
            }
            if (mid - Vector3::repeat(1.0)).norm() < 2.0 {
                assert!(cut[t], "tet {t} in the corner's air is walked");
            }
            for (k, &l) in raycaster.links[t].iter().enumerate() {
                assert!(l < 0 || !cut[(l >> 2) as usize], "tet {t} links to a cut tet");
                let boundary = raycaster.boundary.contains(&(t as u32 * 4 + k as u32));
                assert_eq!(boundary, !cut[t] && l < 0, "tet {t} face {k}: boundary {boundary}");
            }
        }
        assert!(pocket > 0);
        assert!(cut.iter().filter(|&&c| c).count() > mesh.tets().len() / 3, "little air was cut");
    }

    #[test]
    fn a_camera_outside_the_mesh_bins_only_the_faces_rays_enter_through() {
        let (mesh, scalars) = ball_in_air();
        let raycaster = TetRaycaster::new(&mesh, &scalars, &tissue(), &TetRaycastParams::default()).unwrap();
        let look = |eye: Vector3<f64>, projection| onto_ball(eye, projection, [40, 30]);
        let outside = [
            look(Vector3::new(-40.0, -55.0, 30.0), Projection::Perspective { fov_y_deg: 30.0 }),
            look(Vector3::new(50.0, -20.0, -35.0), Projection::Orthographic { height: 30.0 }),
        ];
        let all = raycaster.boundary.len();
        for camera in &outside {
            let kept = raycaster.first_faces(camera);
            assert!(kept.len() > all / 3 && kept.len() < all * 2 / 3, "{} of {all} faces kept", kept.len());
            // No ray of the camera crosses a dropped face going in.
            for &f in raycaster.boundary.iter().filter(|f| !kept.contains(f)) {
                let plane = &raycaster.geometry[(f >> 2) as usize].planes[(f & 3) as usize];
                for (px, py) in (0..40).flat_map(|x| (0..30).map(move |y| (x, y))) {
                    let (origin, direction) = camera.ray(px, py);
                    let o = (origin.coords - raycaster.anchor).cast::<f32>();
                    let (denom, t) = plane_t(plane, &o, &direction.cast::<f32>());
                    assert!(!(denom < 0.0 && t > 0.0), "face {f} dropped, but pixel ({px}, {py}) enters through it");
                }
            }
        }
        // The eye in the tissue: a ray's first face is an exit, so every face is kept.
        let inside = look(Vector3::new(6.0, 0.0, 0.0), Projection::Perspective { fov_y_deg: 60.0 });
        assert_eq!(raycaster.first_faces(&inside), raycaster.boundary);
    }

    #[test]
    fn cutting_the_air_changes_no_pixel() {
        let (mesh, scalars) = ball_in_air();
        let cameras = [
            onto_ball(Vector3::new(-40.0, -55.0, 30.0), Projection::Perspective { fov_y_deg: 30.0 }, [400, 400]),
            onto_ball(Vector3::new(50.0, -20.0, -35.0), Projection::Orthographic { height: 30.0 }, [400, 300]),
        ];
        for preintegrated in [true, false] {
            let params = TetRaycastParams { preintegrated, step: 1.0, early_termination: 1.0, ..Default::default() };
            let cut = TetRaycaster::new(&mesh, &scalars, &tissue(), &params).unwrap();
            let mut whole = TetRaycaster::new(&mesh, &scalars, &tissue(), &params).unwrap();
            whole.links = ordered(&mesh).2;
            whole.walked = vec![true; whole.links.len()];
            whole.boundary = boundary_faces(&whole.links, &whole.walked);
            whole.update(mesh.nodes()).unwrap();
            assert!(cut.boundary.len() != whole.boundary.len());
            for camera in &cameras {
                let (a, b) = (cut.render(camera).unwrap(), whole.render(camera).unwrap());
                let lit = a.rgba.chunks_exact(4).filter(|p| p[0] > 40).count();
                assert!(lit > a.rgba.len() / 4 / 10, "the view is nearly empty ({lit} pixels)");
                for (i, (p, q)) in a.rgba.chunks_exact(4).zip(b.rgba.chunks_exact(4)).enumerate() {
                    let worst = p.iter().zip(q).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0);
                    assert!(worst <= 1, "pixel {i}: {p:?} cut, {q:?} whole (pre-integrated {preintegrated})");
                    let (da, db) = (a.depth[i], b.depth[i]);
                    assert!(da == db || (da - db).abs() <= 1e-3 * da.abs(), "pixel {i}: depth {da} cut, {db} whole");
                }
            }
        }
    }

    /// The walk eight rays at a time gives the one-ray walk's colours and depths to the bit:
    /// from outside (perspective and orthographic), from the air pocket inside the ball (rays
    /// start inside the mesh and leave and re-enter it), with a tool ending rays in the
    /// tissue, segments longer than the table reaches (a 0.1 mm step) and rays turning
    /// opaque (dense tissue).
    #[test]
    fn eight_lanes_give_the_one_ray_walks_bits() {
        let (mesh, scalars) = ball_in_air();
        let pocket = Vector3::new(0.5, -1.0, 0.7);
        let cameras = [
            onto_ball(Vector3::new(-40.0, -55.0, 30.0), Projection::Perspective { fov_y_deg: 30.0 }, [203, 150]),
            onto_ball(Vector3::new(50.0, -20.0, -35.0), Projection::Orthographic { height: 30.0 }, [120, 97]),
            onto_ball(pocket, Projection::Perspective { fov_y_deg: 70.0 }, [96, 64]),
        ];
        let tool = ToolPicture { tip: [14.0, 8.0, 14.0], tail: [14.0, -20.0, 14.0], radius: 2.0, color: [0.5; 3] };
        let dense = TransferFunction {
            points: tissue().points.iter().map(|p| TfPoint { opacity: p.opacity * 6.0, ..*p }).collect(),
            ..tissue()
        };
        let scenes = [
            (tissue(), TetRaycastParams::default()),
            (tissue(), TetRaycastParams { tools: vec![tool], ..Default::default() }),
            (tissue(), TetRaycastParams { step: 0.1, ..Default::default() }),
            (dense, TetRaycastParams::default()),
        ];
        let (mut opaque, mut at_tool) = (0, 0);
        for (tf, params) in &scenes {
            let raycaster = TetRaycaster::new(&mesh, &scalars, tf, params).unwrap();
            if !raycaster.lanes_walk() {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            }
            for camera in &cameras {
                let one = lanes_against_one_ray(&raycaster, camera);
                opaque += one.iter().filter(|r| r.ray.acc[3] >= 0.999).count();
                at_tool += one.iter().filter(|r| r.ray.t_stop.is_finite() && r.ray.acc[3] > 0.05).count();
            }
        }
        assert!(opaque > 100 && at_tool > 100, "{opaque} rays turned opaque, {at_tool} met the tool in tissue");
    }

    /// The source through the mesh walked eight rays side by side gives the one-ray walk's
    /// picture to the bit, pre-integrated and point sampled: every pixel's colour and depth,
    /// the mesh bent (so each tet maps its samples its own way), seen from outside
    /// (perspective and orthographic) and from the air pocket inside the ball, with a tool
    /// ending rays in the tissue, a step longer than most tets (runs of no samples), tets
    /// the source leaves invisible (pre-integrated, only their first and last samples
    /// read; point sampled, none), rays turning opaque, a source that ends inside the
    /// mesh (samples outside it neither add nor make fronts), and pictures shaded by the
    /// gradient and the forward difference (the eye's light and one of their own).
    #[test]
    fn eight_source_lanes_give_the_one_ray_walks_bits() {
        let (mesh, _) = ball_in_air();
        let (volume, params, tf) = shell();
        let centre = Vector3::repeat(14.0);
        let bent: Vec<Vector3<f64>> = mesh
            .nodes()
            .iter()
            .map(|p| {
                p + Vector3::new(0.08 * (p.z - 14.0).powi(2) / 14.0, 0.6 * (0.3 * p.x).sin(), 0.0) * (p - centre).norm()
                    / 10.0
            })
            .collect();
        let pocket = Vector3::new(0.5, -1.0, 0.7);
        let cameras = [
            onto_ball(Vector3::new(-16.0, -22.0, 12.0), Projection::Perspective { fov_y_deg: 30.0 }, [203, 150]),
            onto_ball(Vector3::new(25.0, -10.0, -18.0), Projection::Orthographic { height: 17.0 }, [120, 97]),
            onto_ball(pocket, Projection::Perspective { fov_y_deg: 70.0 }, [96, 64]),
        ];
        let tool = ToolPicture { tip: [14.0, 8.0, 14.0], tail: [14.0, -20.0, 14.0], radius: 2.0, color: [0.5; 3] };
        let dense = TransferFunction {
            points: tf.points.iter().map(|p| TfPoint { opacity: p.opacity * 6.0, ..*p }).collect(),
            ..tf.clone()
        };
        // The shell's lower 40 of 57 slices: its top (z > 19.5 mm) lies in the mesh.
        let slices = 57 * 57 * 40;
        let lower = Volume::new(
            [57, 57, 40],
            [0.5; 3],
            [0.0; 3],
            Matrix3::identity(),
            volume.data()[..slices].to_vec(),
            "lower",
        );
        let lower = Arc::new(lower.unwrap());
        let point = RaycastParams { preintegrated: false, ..params.clone() };
        // A light of its own (each ray's, toward the eye, where none), off every axis.
        let lit = Some([0.3, -0.8, 0.5]);
        let scenes = [
            (&volume, tf.clone(), params.clone()),
            (&volume, tf.clone(), RaycastParams { tools: vec![tool], ..params.clone() }),
            (&volume, tf.clone(), RaycastParams { step: 2.5, ..params.clone() }),
            (&volume, dense.clone(), RaycastParams { early_termination: 0.95, ..params.clone() }),
            (&lower, tf.clone(), params.clone()),
            (&volume, tf.clone(), RaycastParams { tools: vec![tool], ..point.clone() }),
            (&volume, dense, RaycastParams { step: 2.5, early_termination: 0.95, ..point.clone() }),
            (&lower, tf.clone(), point.clone()),
            (&volume, tf.clone(), RaycastParams { shading: Shading::Gradient, ..params.clone() }),
            (&lower, tf.clone(), RaycastParams { shading: Shading::Gradient, light: lit, ..point.clone() }),
            (&volume, tf.clone(), RaycastParams { shading: Shading::ForwardDifference, tools: vec![tool], ..params }),
            (&lower, tf.clone(), RaycastParams { shading: Shading::ForwardDifference, light: lit, ..point }),
        ];
        let (mut opaque, mut at_tool) = (0, 0);
        for (volume, tf, params) in scenes {
            let sampling = SourceSampling::default();
            let mut raycaster = TetRaycaster::with_source(&mesh, volume.clone(), &tf, &params, &sampling).unwrap();
            raycaster.update(&bent).unwrap();
            if !raycaster.source_lanes_walk() {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            }
            for camera in &cameras {
                let one = lanes_against_one_ray(&raycaster, camera);
                opaque += one.iter().filter(|r| r.ray.acc[3] >= 0.95).count();
                at_tool += one.iter().filter(|r| r.ray.t_stop.is_finite() && r.ray.acc[3] > 0.05).count();
            }
        }
        assert!(opaque > 100 && at_tool > 100, "{opaque} rays turned opaque, {at_tool} met the tool in tissue");
    }

    /// Every ray of `camera` cast by `raycaster` eight lanes at a time and one by one: each
    /// pixel's colour and depth the same to the bit, in a view that is not nearly empty.
    /// The rays cast one by one, to count what the scene exercised.
    fn lanes_against_one_ray(raycaster: &TetRaycaster, camera: &Camera) -> Vec<StripRay> {
        let cast_all = |lanes: bool| {
            let bins = bin_boundary(&raycaster.tets, &raycaster.first_faces(camera), &raycaster.positions, camera);
            let rays = camera.rays();
            let strips = (0..bins.tiles[1]).map(|row| raycaster.cast_strip_rays(&bins, &rays, row, lanes));
            strips.flatten().collect::<Vec<_>>()
        };
        let (lanes, one) = (cast_all(true), cast_all(false));
        let seen = one.iter().filter(|r| r.ray.acc[3] > 0.05).count();
        assert!(seen > one.len() / 10, "the view is nearly empty ({seen} rays)");
        for (a, b) in lanes.iter().zip(&one) {
            assert_eq!(a.pixel, b.pixel);
            let ((ca, da), (cb, db)) = (a.ray.finish(), b.ray.finish());
            let bits = |c: [f32; 4], d: f32| (c.map(f32::to_bits), d.to_bits());
            assert_eq!(bits(ca, da), bits(cb, db), "pixel {}: {ca:?} {da} lanes, {cb:?} {db} one by one", a.pixel);
        }
        one
    }

    /// `mesh` with its tets listed in a random order.
    fn shuffled(mesh: &TetMesh) -> TetMesh {
        let mut tets = mesh.tets().to_vec();
        fastrand::Rng::with_seed(38).shuffle(&mut tets);
        TetMesh::new(mesh.nodes().to_vec(), tets, None, "shuffled").unwrap()
    }

    /// A mesh listing its tets in no spatial order renders the ordered mesh's picture to
    /// the bit (the raycaster keeps both in one order), itself close to the f64 reference.
    #[test]
    fn a_mesh_in_no_spatial_order_renders_as_the_ordered_one() {
        let (mesh, scalars) = ball_in_air();
        let shuffled = shuffled(&mesh);
        let camera =
            onto_ball(Vector3::new(-40.0, -55.0, 30.0), Projection::Perspective { fov_y_deg: 30.0 }, [200, 200]);
        let params = TetRaycastParams { step: 1.0, ..Default::default() };
        let render = |mesh: &TetMesh| TetRaycaster::new(mesh, &scalars, &tissue(), &params).unwrap().render(&camera);
        let (a, b) = (render(&mesh).unwrap(), render(&shuffled).unwrap());
        assert!(a.rgba == b.rgba && a.depth == b.depth, "the shuffled mesh's picture differs");
        let reference = reference(&mesh, mesh.nodes(), &scalars, &camera, &tissue(), &params).unwrap();
        let psnr = a.psnr(&reference);
        assert!(psnr > 40.0, "{psnr} dB against the f64 walk");
    }

    /// A shell of tissue (3 to 7 mm from the centre of [`ball_in_air`]'s lattice) sampled
    /// every ½ mm over the lattice's 28 mm box, its macro cells (4 mm) leaving the corners'
    /// air invisible; the parameters and transfer function to see it through the mesh.
    fn shell() -> (Arc<Volume>, RaycastParams, TransferFunction) {
        let n = 57;
        let data = (0..n * n * n)
            .map(|i| {
                let p = Vector3::new((i % n) as f64, ((i / n) % n) as f64, (i / (n * n)) as f64) * 0.5;
                let r = (p - Vector3::repeat(14.0)).norm();
                let bump = (0.7 * p.x).sin() * (0.5 * p.y).cos();
                if r < 3.0 || r > 7.0 + bump {
                    AIR
                } else {
                    (100.0 + 60.0 * (0.4 * p.z).sin()) as f32
                }
            })
            .collect();
        let volume = Arc::new(Volume::new([n; 3], [0.5; 3], [0.0; 3], Matrix3::identity(), data, "shell").unwrap());
        let params = RaycastParams { step: 0.5, early_termination: 1.0, shading: Shading::None, ..Default::default() };
        // Transparent up to 50: the macro cells' visibility is one table entry wide.
        let mut tf = tissue();
        tf.points.insert(1, TfPoint { value: 50.0, color: [0.2, 0.3, 0.9], opacity: 0.0 });
        (volume, params, tf)
    }

    /// The source seen through a mesh listing its tets in no spatial order: the ordered
    /// mesh's picture to the bit (the tets' source visibility follows them into the
    /// raycaster's order).
    #[test]
    fn a_source_through_a_mesh_in_no_spatial_order_renders_as_through_the_ordered_one() {
        let (mesh, _) = ball_in_air();
        let shuffled = shuffled(&mesh);
        let (volume, params, tf) = shell();
        let camera =
            onto_ball(Vector3::new(-16.0, -22.0, 12.0), Projection::Perspective { fov_y_deg: 30.0 }, [120, 120]);
        let render = |mesh: &TetMesh| {
            let sampling = SourceSampling::default();
            TetRaycaster::with_source(mesh, volume.clone(), &tf, &params, &sampling).unwrap().render(&camera).unwrap()
        };
        let (a, b) = (render(&mesh), render(&shuffled));
        let lit = a.rgba.chunks_exact(4).filter(|p| p[0] > 40).count();
        assert!(lit > 120 * 120 / 10, "the view is nearly empty ({lit} pixels)");
        assert!(a.rgba == b.rgba && a.depth == b.depth, "the shuffled mesh's picture differs");
    }

    /// The source through the mesh: the air around the tissue is cut as for node scalars
    /// (from the tets' source visibility), and the picture is as close to the f64 reference
    /// as when rays walk the air (they now start at the tissue, their samples' grid with
    /// them).
    #[test]
    fn the_air_around_a_source_is_cut_at_the_accuracy_of_walking_it() {
        let (mesh, _) = ball_in_air();
        let (volume, params, tf) = shell();
        let sampling = SourceSampling::default();
        let cut = TetRaycaster::with_source(&mesh, volume.clone(), &tf, &params, &sampling).unwrap();
        let mut whole = TetRaycaster::with_source(&mesh, volume.clone(), &tf, &params, &sampling).unwrap();
        whole.links = ordered(&mesh).2;
        whole.walked = vec![true; whole.links.len()];
        whole.boundary = boundary_faces(&whole.links, &whole.walked);
        whole.update(mesh.nodes()).unwrap();
        let cut_tets = cut.walked.iter().filter(|w| !**w).count();
        assert!(cut_tets > mesh.tets().len() / 4, "{cut_tets} of {} tets cut", mesh.tets().len());
        let visible = &cut.source.as_ref().unwrap().visible;
        assert_eq!(visible.len(), cut.walked.len());
        assert!(cut.walked.iter().zip(visible).all(|(w, v)| *w || *v == 0), "a tet that may be seen is cut");
        let camera =
            onto_ball(Vector3::new(-16.0, -22.0, 12.0), Projection::Perspective { fov_y_deg: 30.0 }, [120, 120]);
        let (a, b) = (cut.render(&camera).unwrap(), whole.render(&camera).unwrap());
        let lit = a.rgba.chunks_exact(4).filter(|p| p[0] > 40).count();
        assert!(lit > 120 * 120 / 10, "the view is nearly empty ({lit} pixels)");
        let fine = RaycastParams { step: 0.05, ..params.clone() };
        let exact = crate::mesh::source::reference(&mesh, mesh.nodes(), &volume, &camera, &tf, &fine, &[]).unwrap();
        let ((cut_mean, cut_max), (whole_mean, whole_max)) = (a.errors(&exact), b.errors(&exact));
        let errors = format!("cut mean {cut_mean:.3}, max {cut_max:.1}; whole {whole_mean:.3}, {whole_max:.1} levels");
        eprintln!("against the f64 reference: {errors}");
        assert!(cut_mean <= 1.05 * whole_mean && cut_max <= whole_max + 2.0, "{errors}");
    }
}
