//! Tools against the mesh's **boundary surface**, so that instruments thinner than the mesh
//! spacing (a 1-2 mm needle against 5-20 mm tets) are felt between nodes.
//!
//! The tool's collision model is the one surgical simulators (SOFA) use: spheres of the
//! tool's radius sampled along its core. Each sphere is held out of the faces near it as a
//! god-object proxy is held by its constraint planes (`sample_contacts`); the penalty force
//! `k φ` goes to the holding faces' nodes by barycentric weights and the planes' shares,
//! and the tool feels the sum pushed back. Inside or outside is decided with angle-weighted
//! pseudo-normals (Bærentzen & Aanæs), so a sample that went past the surface is pushed
//! back out rather than through. Boundary
//! nodes inside a wide tool (wider than the spacing) are pushed out one by one besides,
//! so a large probe dents a patch rather than one point.
//!
//! The broad phase is a bounding-volume hierarchy over the boundary faces, built once on
//! the rest shape. It is refitted to the deformed shape only once the nodes may have
//! drifted half a spacing from where its boxes were fitted; until then every box is read
//! grown by that drift, which keeps it conservative. Positions are read one node at a time
//! (`Positions`), so a query touches the few faces near the tool and copies nothing,
//! whatever the mesh's size.

use std::collections::HashMap;

use nalgebra::Vector3;

/// What the contact kernel needs of a tool.
#[derive(Debug, Clone, Copy)]
pub struct ContactParams {
    pub a: Vector3<f64>,
    pub b: Vector3<f64>,
    pub radius: f64,
    pub stiffness: f64,
}

impl ContactParams {
    /// Penalty contact at `p`: (force, unit normal) when `p` is inside the shape.
    pub fn contact(&self, p: &Vector3<f64>) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let d = p - closest_on_segment(&self.a, &self.b, p);
        let dist = d.norm();
        if dist >= self.radius {
            return None;
        }
        // A node exactly on the core has no defined normal: push it along +z of the world,
        // any fixed choice keeps the step deterministic.
        let n = if dist > 1e-12 { d / dist } else { Vector3::z() };
        Some((n * (self.stiffness * (self.radius - dist)), n))
    }
}

/// Node positions read one at a time, so that a query near the tool reads the nodes near
/// it and never copies the whole mesh's.
pub trait Positions {
    fn at(&self, node: u32) -> Vector3<f64>;
}

impl Positions for [Vector3<f64>] {
    fn at(&self, node: u32) -> Vector3<f64> {
        self[node as usize]
    }
}

/// The hierarchy is refitted once the nodes may have drifted this many spacings from where
/// its boxes were fitted: queries grow with the drift, refits are whole-surface passes.
const REFIT_DRIFT: f64 = 0.5;

/// Faces per leaf of the hierarchy.
const LEAF: usize = 4;
/// Barycentric weights below this are zero: the closest point lies on an edge or a node.
const ON_FEATURE: f64 = 1e-9;

/// The most nodes one contact spreads over: the ring of faces around a node of valence up
/// to 15, on which a sphere may rest all at once.
pub const CONTACT_NODES: usize = 16;

/// One contact of a tool sample with the surface. The surface is pushed along `push` with
/// force `stiffness · depth`, spread over `nodes` by `shares`; the tool gets the opposite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceContact {
    pub tool: usize,
    /// The nodes the force is spread over; `u32::MAX` past the last.
    pub nodes: [u32; CONTACT_NODES],
    /// Each node's part of the force per unit `stiffness · depth`, summing to `push`: w·n
    /// for a node of barycentric weight w on a face pushed along n. Also the gradient of
    /// the penetration φ with respect to the node's position, negated.
    pub shares: [Vector3<f64>; CONTACT_NODES],
    /// Unit direction in which the surface is pushed (into the body); the gradient of φ
    /// with respect to the tool's position.
    pub push: Vector3<f64>,
    /// Penetration φ > 0 (m); ≤ 0 for a contact about to begin.
    pub depth: f64,
    /// A row with no force of its own (depth 0) that carries the rest of the stiffness of
    /// a sphere held by several planes, across them, into the implicit step; it stands or
    /// falls with the contact before it.
    pub joins_previous: bool,
    pub stiffness: f64,
    /// The contact point on the surface (world), for torques.
    pub at: Vector3<f64>,
}

impl SurfaceContact {
    /// A contact pushing `nodes` by barycentric `weights` along `push`.
    fn on_feature(tool: &ToolCore, nodes: &[u32], weights: &[f64], push: Vector3<f64>, depth: f64) -> Self {
        let mut contact = Self {
            tool: tool.tool,
            nodes: [u32::MAX; CONTACT_NODES],
            shares: [Vector3::zeros(); CONTACT_NODES],
            push,
            depth,
            joins_previous: false,
            stiffness: tool.core.stiffness,
            at: Vector3::zeros(),
        };
        for (k, (&node, &w)) in nodes.iter().zip(weights).enumerate() {
            contact.nodes[k] = node;
            contact.shares[k] = push * w;
        }
        contact
    }

    /// Adds `share` to `node`'s, taking the next free slot for a node not yet in (`Hold`
    /// never brings in more nodes than there are slots).
    fn add_share(&mut self, node: u32, share: Vector3<f64>) {
        if let Some(k) = self.nodes.iter().position(|&m| m == node || m == u32::MAX) {
            self.nodes[k] = node;
            self.shares[k] += share;
        }
    }

    /// The force on the surface (N); the tool gets its negative.
    pub fn force(&self) -> Vector3<f64> {
        self.push * (self.stiffness * self.depth)
    }

    /// Each node with its part of `force` (N).
    pub fn node_forces(&self) -> impl Iterator<Item = (u32, Vector3<f64>)> + '_ {
        let scale = self.stiffness * self.depth;
        (self.nodes.iter().zip(&self.shares)).take_while(|(n, _)| **n != u32::MAX).map(move |(&n, s)| (n, s * scale))
    }
}

/// A tool as the detection sees it: its index and its core, in world coordinates.
#[derive(Debug, Clone, Copy)]
pub struct ToolCore {
    pub tool: usize,
    pub core: ContactParams,
}

#[derive(Debug, Clone, Copy)]
struct BvhNode {
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    /// Leaf: faces `order[start..start + count]`; inner (count 0): left child is the next
    /// node, right child is `start`.
    start: u32,
    count: u32,
}

/// The boundary surface with its broad phase and the adjacency pseudo-normals need.
#[derive(Debug, Clone)]
pub struct Surface {
    faces: Vec<[u32; 3]>,
    /// For node i, the faces around it: `node_faces[node_offsets[i]..node_offsets[i+1]]`.
    node_offsets: Vec<u32>,
    node_faces: Vec<u32>,
    /// For each face, the face across its edge opposite each of its vertices.
    partners: Vec<[u32; 3]>,
    bvh: Vec<BvhNode>,
    order: Vec<u32>,
    spacing: f64,
    /// How far any node may have moved since the boxes were fitted (m): every box is read
    /// grown by it.
    drift: f64,
}

/// For each face, the face across its edge opposite each of its vertices. Where more than
/// two faces meet at an edge (two bodies touching along it, as meshes cut from a
/// segmentation do), each is paired with the face that closes the same wedge of material
/// around the edge, so each body keeps its own pseudo-normal there; a face left unpaired
/// is its own partner.
fn edge_partners(faces: &[[u32; 3]], rest: &[Vector3<f64>]) -> Vec<[u32; 3]> {
    let mut around: HashMap<[u32; 2], Vec<(u32, usize)>> = HashMap::new();
    for (f, face) in faces.iter().enumerate() {
        for k in 0..3 {
            let (i, j) = (face[(k + 1) % 3], face[(k + 2) % 3]);
            around.entry([i.min(j), i.max(j)]).or_default().push((f as u32, k));
        }
    }
    let mut partners: Vec<[u32; 3]> = (0..faces.len() as u32).map(|f| [f; 3]).collect();
    for (edge, sharing) in around {
        if let [(f, k), (g, l)] = sharing[..] {
            partners[f as usize][k] = g;
            partners[g as usize][l] = f;
        } else {
            pair_around_edge(edge, &sharing, faces, rest, &mut partners);
        }
    }
    partners
}

/// Pairs the faces around a non-manifold edge: sorted by angle about it, each face's body
/// lies ahead of it or behind it, and it is paired with its neighbour on that side when
/// that neighbour's body lies back towards it.
fn pair_around_edge(
    edge: [u32; 2],
    sharing: &[(u32, usize)],
    faces: &[[u32; 3]],
    rest: &[Vector3<f64>],
    partners: &mut [[u32; 3]],
) {
    let a = rest[edge[0] as usize];
    let Some(axis) = (rest[edge[1] as usize] - a).try_normalize(0.0) else { return };
    let u = axis.cross(&if axis.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
    let v = axis.cross(&u);
    let mut fan: Vec<(f64, u32, usize, bool)> = sharing
        .iter()
        .map(|&(f, k)| {
            let [p, q, r] = faces[f as usize].map(|n| rest[n as usize]);
            let wing = rest[faces[f as usize][k] as usize] - a;
            let outward = (q - p).cross(&(r - p));
            // The body is on the inward side; ahead means towards increasing angle.
            let ahead = -outward.dot(&axis.cross(&wing)) > 0.0;
            (wing.dot(&v).atan2(wing.dot(&u)), f, k, ahead)
        })
        .collect();
    fan.sort_by(|x, y| x.0.total_cmp(&y.0));
    let m = fan.len();
    for (n, &(_, f, k, ahead)) in fan.iter().enumerate() {
        let (_, g, _, g_ahead) = fan[if ahead { (n + 1) % m } else { (n + m - 1) % m }];
        if g_ahead != ahead {
            partners[f as usize][k] = g;
        }
    }
}

impl Surface {
    /// The surface of `faces` (outward-oriented boundary triangles) over `rest` positions.
    pub fn new(faces: &[[u32; 3]], rest: &[Vector3<f64>]) -> Self {
        let mut node_offsets = vec![0u32; rest.len() + 1];
        for f in faces {
            for &i in f {
                node_offsets[i as usize + 1] += 1;
            }
        }
        for i in 0..rest.len() {
            node_offsets[i + 1] += node_offsets[i];
        }
        let mut cursor = node_offsets.clone();
        let mut node_faces = vec![0u32; node_offsets[rest.len()] as usize];
        let mut length = 0.0;
        for (fi, f) in faces.iter().enumerate() {
            for (k, &i) in f.iter().enumerate() {
                node_faces[cursor[i as usize] as usize] = fi as u32;
                cursor[i as usize] += 1;
                length += (rest[f[(k + 1) % 3] as usize] - rest[i as usize]).norm();
            }
        }
        let spacing = if faces.is_empty() { 0.0 } else { length / (3 * faces.len()) as f64 };
        let mut surface = Self {
            faces: faces.to_vec(),
            node_offsets,
            node_faces,
            partners: edge_partners(faces, rest),
            bvh: Vec::new(),
            order: (0..faces.len() as u32).collect(),
            spacing,
            drift: 0.0,
        };
        if !faces.is_empty() {
            let centroids: Vec<Vector3<f64>> =
                faces.iter().map(|f| f.iter().map(|&i| rest[i as usize]).sum::<Vector3<f64>>() / 3.0).collect();
            let mut order = std::mem::take(&mut surface.order);
            surface.build(&mut order, 0, &centroids);
            surface.order = order;
            surface.refit(rest);
        }
        surface
    }

    /// Mean boundary edge length (m).
    pub fn spacing(&self) -> f64 {
        self.spacing
    }

    /// Top-down median split on the longest axis of the centroids; pre-order layout.
    fn build(&mut self, order: &mut [u32], start: usize, centroids: &[Vector3<f64>]) -> usize {
        let index = self.bvh.len();
        let zero = Vector3::zeros();
        if order.len() <= LEAF {
            self.bvh.push(BvhNode { lo: zero, hi: zero, start: start as u32, count: order.len() as u32 });
            return index;
        }
        self.bvh.push(BvhNode { lo: zero, hi: zero, start: 0, count: 0 });
        let (lo, hi) = defvol_core::mesh::bounds(&order.iter().map(|&f| centroids[f as usize]).collect::<Vec<_>>());
        let axis = (hi - lo).imax();
        let mid = order.len() / 2;
        order.select_nth_unstable_by(mid, |a, b| centroids[*a as usize][axis].total_cmp(&centroids[*b as usize][axis]));
        let (left, right) = order.split_at_mut(mid);
        self.build(left, start, centroids);
        let right_index = self.build(right, start + mid, centroids);
        self.bvh[index].start = right_index as u32;
        index
    }

    /// The nodes moved by at most `distance` (m) since the last call (infinite: unknown);
    /// the boxes are read grown by the sum until `keep_fitted` refits them.
    pub fn moved(&mut self, distance: f64) {
        self.drift += distance;
    }

    /// Refits the boxes to `positions` once the drift has passed `REFIT_DRIFT` spacings;
    /// called before queries, so a mesh no query reads is never refitted.
    pub fn keep_fitted<P: Positions + ?Sized>(&mut self, positions: &P) {
        if self.drift.is_nan() || self.drift > REFIT_DRIFT * self.spacing {
            self.refit(positions);
        }
    }

    /// Boxes around the faces at `positions` (children come after their parent).
    pub fn refit<P: Positions + ?Sized>(&mut self, positions: &P) {
        for n in (0..self.bvh.len()).rev() {
            let node = self.bvh[n];
            let (lo, hi) = if node.count > 0 {
                let range = node.start as usize..(node.start + node.count) as usize;
                let corners = self.order[range].iter().flat_map(|&f| self.faces[f as usize]);
                let mut lo = Vector3::repeat(f64::INFINITY);
                let mut hi = Vector3::repeat(f64::NEG_INFINITY);
                for i in corners {
                    lo = lo.inf(&positions.at(i));
                    hi = hi.sup(&positions.at(i));
                }
                (lo, hi)
            } else {
                let (l, r) = (self.bvh[n + 1], self.bvh[node.start as usize]);
                (l.lo.inf(&r.lo), l.hi.sup(&r.hi))
            };
            self.bvh[n].lo = lo;
            self.bvh[n].hi = hi;
        }
        self.drift = 0.0;
    }

    /// Node `n`'s box as it may be now: grown by the drift since it was fitted.
    fn node_box(&self, n: usize) -> (Vector3<f64>, Vector3<f64>) {
        let grow = Vector3::repeat(self.drift);
        (self.bvh[n].lo - grow, self.bvh[n].hi + grow)
    }

    /// Calls `visit` for every face whose box comes within `reach` of the box [lo, hi].
    fn faces_near(&self, lo: Vector3<f64>, hi: Vector3<f64>, mut visit: impl FnMut(u32)) {
        if self.bvh.is_empty() {
            return;
        }
        let mut stack = vec![0usize];
        while let Some(n) = stack.pop() {
            let node = &self.bvh[n];
            let (node_lo, node_hi) = self.node_box(n);
            if (0..3).any(|a| node_hi[a] < lo[a] || node_lo[a] > hi[a]) {
                continue;
            }
            if node.count > 0 {
                for &f in &self.order[node.start as usize..(node.start + node.count) as usize] {
                    visit(f);
                }
            } else {
                stack.push(node.start as usize);
                stack.push(n + 1);
            }
        }
    }

    fn face_normal<P: Positions + ?Sized>(&self, f: u32, x: &P) -> Vector3<f64> {
        let [a, b, c] = self.faces[f as usize].map(|i| x.at(i));
        (b - a).cross(&(c - a)).try_normalize(0.0).unwrap_or_else(Vector3::zeros)
    }

    /// Whether `p` lies inside the closed surface at `x` (the boxes fitted as `moved`
    /// keeps them): the side of its nearest feature that feature's pseudo-normal says
    /// (Bærentzen & Aanæs 2005), exact for a closed manifold surface, as the contacts
    /// decide it. The nearest face costs a descent of the hierarchy, not a pass over it.
    pub fn encloses<P: Positions + ?Sized>(&self, p: &Vector3<f64>, x: &P) -> bool {
        self.nearest_face(p, x).is_some_and(|f| (p - f.at).dot(&self.feature_normal(f.face, &f.weights, x)) < 0.0)
    }

    /// The face nearest `p` (ties to the lowest face): best first down the hierarchy, a
    /// box skipped once its distance (less the drift) passes the nearest face found.
    fn nearest_face<P: Positions + ?Sized>(&self, p: &Vector3<f64>, x: &P) -> Option<NearFace> {
        let box_distance = |n: usize| {
            let (lo, hi) = self.node_box(n);
            (lo - p).sup(&(p - hi)).sup(&Vector3::zeros()).norm()
        };
        let mut best: Option<NearFace> = None;
        let mut stack = if self.bvh.is_empty() { Vec::new() } else { vec![(0usize, box_distance(0))] };
        while let Some((n, lower)) = stack.pop() {
            if best.as_ref().is_some_and(|b| lower > b.distance) {
                continue;
            }
            let node = self.bvh[n];
            if node.count == 0 {
                let (left, right) = (n + 1, node.start as usize);
                let (dl, dr) = (box_distance(left), box_distance(right));
                // The nearer child on top of the stack, searched first.
                stack.extend(if dl <= dr { [(right, dr), (left, dl)] } else { [(left, dl), (right, dr)] });
                continue;
            }
            for &face in &self.order[node.start as usize..(node.start + node.count) as usize] {
                let [a, b, c] = self.faces[face as usize].map(|i| x.at(i));
                let (at, weights) = closest_on_triangle(p, &a, &b, &c);
                let distance = (p - at).norm();
                let nearer = best.as_ref().is_none_or(|b| (distance, face) < (b.distance, b.face));
                if nearer {
                    best = Some(NearFace { face, at, weights, distance });
                }
            }
        }
        best
    }

    /// Angle-weighted normal of node i: the sign of (p - x_i)·N tells inside from outside
    /// for points whose nearest surface point is the node.
    fn node_normal<P: Positions + ?Sized>(&self, i: u32, x: &P) -> Vector3<f64> {
        let range = self.node_offsets[i as usize] as usize..self.node_offsets[i as usize + 1] as usize;
        self.angle_weighted(i, self.node_faces[range].iter().copied(), x)
    }

    /// [`Self::node_normal`] over the fan of faces around node i that holds face `f`: where
    /// two bodies touch at a node, each keeps its own normal there.
    fn fan_normal<P: Positions + ?Sized>(&self, i: u32, f: u32, x: &P) -> Vector3<f64> {
        let mut fan = vec![f];
        let mut next = 0;
        while let Some(&g) = fan.get(next) {
            next += 1;
            let face = self.faces[g as usize];
            for k in (0..3).filter(|&k| face[k] != i) {
                let across = self.partners[g as usize][k];
                if !fan.contains(&across) {
                    fan.push(across);
                }
            }
        }
        self.angle_weighted(i, fan.into_iter(), x)
    }

    fn angle_weighted<P: Positions + ?Sized>(&self, i: u32, faces: impl Iterator<Item = u32>, x: &P) -> Vector3<f64> {
        let mut sum = Vector3::zeros();
        for f in faces {
            let face = self.faces[f as usize];
            let k = face.iter().position(|&n| n == i).unwrap_or(0);
            let (p, q, r) = (x.at(face[k]), x.at(face[(k + 1) % 3]), x.at(face[(k + 2) % 3]));
            let angle = (q - p).angle(&(r - p));
            sum += self.face_normal(f, x) * angle;
        }
        sum.try_normalize(0.0).unwrap_or_else(Vector3::zeros)
    }

    /// The pseudo-normal of the nearest feature of face `f` at barycentric `w`.
    fn feature_normal<P: Positions + ?Sized>(&self, f: u32, w: &[f64; 3], x: &P) -> Vector3<f64> {
        let face = self.faces[f as usize];
        let zero: Vec<usize> = (0..3).filter(|&k| w[k] <= ON_FEATURE).collect();
        match zero.as_slice() {
            [_, _] => {
                let k = (0..3).find(|k| !zero.contains(k)).unwrap_or(0);
                self.fan_normal(face[k], f, x)
            }
            [k] => {
                let across = self.partners[f as usize][*k];
                (self.face_normal(f, x) + self.face_normal(across, x))
                    .try_normalize(0.0)
                    .unwrap_or_else(|| self.face_normal(f, x))
            }
            _ => self.face_normal(f, x),
        }
    }

    /// Contacts of `tools` with the surface at `positions` (the hierarchy must be refitted
    /// to them), down to depth `-margin` (speculative: a contact about to begin is known to
    /// the implicit step, which evaluates it at the step's end).
    ///
    /// A tool thinner than the spacing is sampled along its core at most half the spacing
    /// apart; each sample is held beyond the faces near it (`sample_contacts`), and where
    /// the core reaches deeper than its samples (a ridge between two of them) the rest is
    /// pushed too (`gap_contacts`). A tool at least as wide as the spacing
    /// always has nodes inside it before anything passes between them: it pushes each
    /// boundary node inside it.
    pub fn detect<P: Positions + ?Sized>(&self, tools: &[ToolCore], positions: &P, margin: f64) -> Vec<SurfaceContact> {
        let mut contacts = Vec::new();
        // A sample up to one spacing past the surface still finds it and is pushed back;
        // one about to touch finds what lies within its margin.
        let reach = self.spacing.max(f64::EPSILON);
        let search = reach.max(margin);
        for tool in tools {
            if tool.core.radius >= self.spacing {
                self.node_contacts(tool, positions, margin, &mut contacts);
                continue;
            }
            let (a, b) = (tool.core.a, tool.core.b);
            let length = (b - a).norm();
            let samples = if length > 0.0 { (2.0 * length / reach).ceil() as usize + 1 } else { 1 };
            let centres: Vec<Vector3<f64>> = (0..samples)
                .map(|s| a + (b - a) * if samples > 1 { s as f64 / (samples - 1) as f64 } else { 0.0 })
                .collect();
            for centre in &centres {
                contacts.extend(self.sample_contacts(tool, centre, search, margin, positions));
            }
            if length > 0.0 {
                contacts.extend(self.gap_contacts(tool, &centres, positions));
            }
        }
        contacts
    }

    /// Where a sampled core reaches deeper than its samples account for (a ridge or a node
    /// between two samples): for each face the core comes within its radius of, from
    /// outside, the core's depth there r - d less what the two samples either side push
    /// along the same direction, Σ (r - s_j)⁺ (n_j·n)⁺. On a plane, a slope or a flat
    /// trough the samples cover it all and nothing is added; over a ridge the rest is, as a
    /// contact on that face (those within a radius of core blended: `GapBlend`), which comes
    /// and goes with no jump in force. None is speculative: a row about to begin, its
    /// samples' share not in its gradient, would push again what they already push.
    fn gap_contacts<P: Positions + ?Sized>(
        &self,
        tool: &ToolCore,
        samples: &[Vector3<f64>],
        x: &P,
    ) -> Vec<SurfaceContact> {
        let ContactParams { a, b, radius, .. } = tool.core;
        let pushes: Vec<(f64, Vector3<f64>)> = samples.iter().map(|s| self.sample_push(s, radius, x)).collect();
        let intervals = (samples.len() - 1) as f64;
        let mut candidates: Vec<(f64, f64, SurfaceContact)> = Vec::new(); // depth, parameter, contact
        let reach = Vector3::repeat(radius);
        self.faces_near(a.inf(&b) - reach, a.sup(&b) + reach, |f| {
            let face = self.faces[f as usize];
            let [p, q, r] = face.map(|i| x.at(i));
            let (t, distance) = segment_triangle_nearest(&a, &b, &p, &q, &r);
            if distance >= radius || distance <= 1e-12 {
                return;
            }
            let core = a + (b - a) * t;
            let (at, weights) = closest_on_triangle(&core, &p, &q, &r);
            let out = (core - at) / distance;
            if out.dot(&self.feature_normal(f, &weights, x)) <= 0.0 {
                return; // The core is inside there: its samples are pushed on through.
            }
            let i = ((t * intervals).floor() as usize).min(samples.len() - 2);
            let covered: f64 = pushes[i..i + 2].iter().map(|(depth, n)| depth * n.dot(&out).max(0.0)).sum();
            let depth = radius - covered - distance;
            if depth > 0.0 {
                let mut contact = SurfaceContact::on_feature(tool, &face, &weights, -out, depth);
                contact.at = at;
                candidates.push((depth, t, contact));
            }
        });
        candidates.sort_unstable_by(|g, h| h.0.total_cmp(&g.0).then(g.1.total_cmp(&h.1)));
        let length = (b - a).norm();
        let mut gaps: Vec<(f64, GapBlend)> = Vec::new();
        for (depth, t, contact) in candidates {
            let weight = depth;
            match gaps.iter_mut().find(|(u, _)| (t - u).abs() * length < radius) {
                Some((_, blend)) => blend.add(&contact, weight),
                None => gaps.push((t, GapBlend::new(contact, weight))),
            }
        }
        gaps.into_iter().map(|(_, blend)| blend.contact()).collect()
    }

    /// How deep a sample sphere of `radius` at `centre` is in the surface, and the way it
    /// is pushed out (from the nearest feature to the centre; through, for a centre past
    /// the surface); no depth when it does not touch.
    fn sample_push<P: Positions + ?Sized>(&self, centre: &Vector3<f64>, radius: f64, x: &P) -> (f64, Vector3<f64>) {
        let Some(nearest) = self.nearest_face(centre, x) else { return (0.0, Vector3::zeros()) };
        let outward = self.feature_normal(nearest.face, &nearest.weights, x);
        let away = match nearest.distance > 1e-12 {
            true => (centre - nearest.at) / nearest.distance,
            false => outward,
        };
        if away.dot(&outward) < 0.0 {
            (radius + nearest.distance, -away)
        } else {
            ((radius - nearest.distance).max(0.0), away)
        }
    }

    fn node_contacts<P: Positions + ?Sized>(&self, tool: &ToolCore, x: &P, margin: f64, out: &mut Vec<SurfaceContact>) {
        let ContactParams { a, b, radius, .. } = tool.core;
        let lo = a.inf(&b) - Vector3::repeat(radius + margin);
        let hi = a.sup(&b) + Vector3::repeat(radius + margin);
        let mut near = Vec::new();
        self.faces_near(lo, hi, |f| near.extend(self.faces[f as usize]));
        near.sort_unstable();
        near.dedup();
        for i in near {
            let p = x.at(i);
            let d = p - closest_on_segment(&a, &b, &p);
            let dist = d.norm();
            if dist >= radius + margin {
                continue;
            }
            let push = if dist > 1e-12 { d / dist } else { -self.node_normal(i, x) };
            let mut contact = SurfaceContact::on_feature(tool, &[i], &[1.0], push, radius - dist);
            contact.at = p;
            out.push(contact);
        }
    }

    /// The contacts of one sphere. Outside the body, every face near it gives a separating
    /// plane (through the face's point nearest the centre, facing the centre: the face lies
    /// wholly behind it), and the sphere is pushed to the nearest place at least its radius
    /// beyond all of them, as a god-object proxy is (Zilles & Salisbury 1995): one push, of
    /// the length it moved, shared among the planes holding it (`Hold`). In a groove the two
    /// walls share one push instead of adding a whole one each, and as the sphere slides the
    /// push moves continuously from face to face, so a probe held still comes to rest. Out
    /// of the body is the side the nearest feature's pseudo-normal says; a centre already
    /// past the surface is pushed on through by that feature alone, never out of the far
    /// side (from inside, no other face's plane separates).
    fn sample_contacts<P: Positions + ?Sized>(
        &self,
        tool: &ToolCore,
        centre: &Vector3<f64>,
        reach: f64,
        margin: f64,
        x: &P,
    ) -> Vec<SurfaceContact> {
        let radius = tool.core.radius;
        let near = self.near_faces(centre, radius + reach, x);
        let Some(nearest) = near.first() else { return Vec::new() };
        let outward = self.feature_normal(nearest.face, &nearest.weights, x);
        let inside = (centre - nearest.at).dot(&outward) < 0.0;
        if inside || nearest.distance >= radius {
            // Inside, or not touching: the nearest face alone, if about to touch (speculative).
            let (towards, depth) =
                if inside { (-1.0, radius + nearest.distance) } else { (1.0, radius - nearest.distance) };
            if depth <= -margin {
                return Vec::new();
            }
            let d = nearest.at - centre;
            let push = if nearest.distance > 1e-12 { d * (towards / nearest.distance) } else { -outward };
            let face = &self.faces[nearest.face as usize];
            let mut contact = SurfaceContact::on_feature(tool, face, &nearest.weights, push, depth);
            contact.at = nearest.at;
            return vec![contact];
        }
        let planes: Vec<(Vector3<f64>, f64)> = (near.iter())
            .map(|f| {
                let n = if f.distance > 1e-12 {
                    (centre - f.at) / f.distance
                } else {
                    self.feature_normal(f.face, &f.weights, x)
                };
                (n, n.dot(&f.at) + radius)
            })
            .collect();
        let corners: Vec<[u32; 3]> = near.iter().map(|f| self.faces[f.face as usize]).collect();
        Hold::new(centre, &planes, &corners, radius)
            .map_or_else(Vec::new, |hold| hold.contacts(tool, &near, &planes, &corners))
    }

    /// The faces within `search` of `centre`, nearest first (ties to the lowest face:
    /// deterministic).
    fn near_faces<P: Positions + ?Sized>(&self, centre: &Vector3<f64>, search: f64, x: &P) -> Vec<NearFace> {
        let mut near = Vec::new();
        let r = Vector3::repeat(search);
        self.faces_near(centre - r, centre + r, |face| {
            let [a, b, c] = self.faces[face as usize].map(|i| x.at(i));
            let (at, weights) = closest_on_triangle(centre, &a, &b, &c);
            let distance = (centre - at).norm();
            if distance <= search {
                near.push(NearFace { face, at, weights, distance });
            }
        });
        near.sort_unstable_by(|a, b| a.distance.total_cmp(&b.distance).then(a.face.cmp(&b.face)));
        near
    }
}

/// The gap contacts of faces within a radius of each other along the core, as one: as deep
/// as the deepest, its push and shares the members' weighted by their depths, so that where two faces are about as deep (either side of a node) the push
/// does not flip from one to the other, and a member comes in with no weight.
struct GapBlend {
    contact: SurfaceContact,
    total: f64,
}

impl GapBlend {
    fn new(mut contact: SurfaceContact, weight: f64) -> Self {
        contact.push *= weight;
        contact.at *= weight;
        contact.shares.iter_mut().for_each(|s| *s *= weight);
        Self { contact, total: weight }
    }

    /// Adds `member` with `weight`, unless its nodes would not fit.
    fn add(&mut self, member: &SurfaceContact, weight: f64) {
        let members = member.nodes.iter().take_while(|&&n| n != u32::MAX);
        let new = members.clone().filter(|n| !self.contact.nodes.contains(n)).count();
        let used = self.contact.nodes.iter().take_while(|&&n| n != u32::MAX).count();
        if used + new > CONTACT_NODES {
            return;
        }
        for (&node, share) in members.zip(&member.shares) {
            self.contact.add_share(node, share * weight);
        }
        self.contact.push += member.push * weight;
        self.contact.at += member.at * weight;
        self.total += weight;
    }

    fn contact(mut self) -> SurfaceContact {
        let scale = 1.0 / self.total;
        self.contact.push *= scale;
        self.contact.at *= scale;
        self.contact.shares.iter_mut().for_each(|s| *s *= scale);
        self.contact
    }
}

/// A face near a sphere: its point nearest the centre, with barycentric weights.
struct NearFace {
    face: u32,
    at: Vector3<f64>,
    weights: [f64; 3],
    distance: f64,
}

/// A sphere held beyond separating planes: which planes hold it, how they share the push
/// (multipliers μ, p − c = Σ μ_j n_j), and the inverse Gram matrix G⁻¹ of their normals.
struct Hold {
    lift: f64,
    holding: Vec<usize>,
    multipliers: nalgebra::DVector<f64>,
    inverse_gram: nalgebra::DMatrix<f64>,
}

impl Hold {
    /// Every plane the held sphere rests on: around a node more than the three the
    /// projection needed, and which three it took would flip with rounding from step to
    /// step; they share the push by the least multipliers that make it when those are all
    /// positive, else by the projection's own.
    fn new(centre: &Vector3<f64>, planes: &[(Vector3<f64>, f64)], corners: &[[u32; 3]], radius: f64) -> Option<Self> {
        let (held, multipliers) = beyond_planes(centre, planes);
        let lift = (held - centre).norm();
        if lift == 0.0 {
            return None;
        }
        let gram = |set: &[usize]| {
            nalgebra::DMatrix::from_fn(set.len(), set.len(), |a, b| planes[set[a]].0.dot(&planes[set[b]].0))
        };
        let resting: Vec<usize> = (0..planes.len())
            .filter(|&j| multipliers[j] > 0.0 || planes[j].0.dot(&held) - planes[j].1 < 1e-9 * radius)
            .collect();
        let violation = nalgebra::DVector::from_iterator(
            resting.len(),
            resting.iter().map(|&j| planes[j].1 - planes[j].0.dot(centre)),
        );
        let mut nodes: Vec<u32> = resting.iter().flat_map(|&j| corners[j]).collect();
        nodes.sort_unstable();
        nodes.dedup();
        let gram_inverse = if nodes.len() <= CONTACT_NODES { gram(&resting).pseudo_inverse(1e-12).ok() } else { None };
        if let Some(inverse_gram) = gram_inverse {
            let least = &inverse_gram * violation;
            if least.iter().all(|m| *m >= 0.0) {
                return Some(Self { lift, holding: resting, multipliers: least, inverse_gram });
            }
        }
        let holding: Vec<usize> = (0..planes.len()).filter(|&j| multipliers[j] > 0.0).collect();
        let inverse_gram = gram(&holding).try_inverse()?;
        let multipliers = nalgebra::DVector::from_iterator(holding.len(), holding.iter().map(|&j| multipliers[j]));
        Some(Self { lift, holding, multipliers, inverse_gram })
    }

    /// The energy ½k gᵀG⁻¹g of the holding planes' violations g as contact rows:
    /// G⁻¹ = u uᵀ + Σ v vᵀ with u = μ/|δ|, whose row is the push (depth |δ|), and rows v of
    /// depth 0 (vᵀg = 0) that carry the stiffness across the planes into the implicit step.
    fn contacts(
        &self,
        tool: &ToolCore,
        near: &[NearFace],
        planes: &[(Vector3<f64>, f64)],
        corners: &[[u32; 3]],
    ) -> Vec<SurfaceContact> {
        let u = &self.multipliers / self.lift;
        let rest = nalgebra::SymmetricEigen::new(&self.inverse_gram - &u * u.transpose());
        let mut rows = vec![(u, self.lift, false)];
        for (k, &lambda) in rest.eigenvalues.iter().enumerate() {
            if lambda > 1e-9 * self.inverse_gram.norm() {
                rows.push((rest.eigenvectors.column(k) * lambda.sqrt(), 0.0, true));
            }
        }
        let total = self.multipliers.sum();
        let at: Vector3<f64> =
            (self.holding.iter().zip(self.multipliers.iter())).map(|(&j, mu)| near[j].at * (mu / total)).sum();
        let row = |(coefficients, depth, joins_previous): (nalgebra::DVector<f64>, f64, bool)| {
            let mut contact = SurfaceContact::on_feature(tool, &[], &[], Vector3::zeros(), depth);
            (contact.at, contact.joins_previous) = (at, joins_previous);
            for (&j, c) in self.holding.iter().zip(coefficients.iter()) {
                let n = planes[j].0;
                contact.push -= n * *c;
                for (&node, w) in corners[j].iter().zip(near[j].weights) {
                    contact.add_share(node, -n * (c * w));
                }
            }
            contact
        };
        rows.into_iter().map(row).collect()
    }
}

/// The point p nearest to `c` with n_j·p ≥ b_j for every plane (n_j, b_j), and the
/// multipliers μ_j ≥ 0 with p - c = Σ μ_j n_j. The dual active-set method of Goldfarb &
/// Idnani (1983) for the identity Hessian: from p = c, the most violated plane is brought in, dropping
/// any active plane whose multiplier would turn negative; in 3-D at most three stay active.
pub fn beyond_planes(c: &Vector3<f64>, planes: &[(Vector3<f64>, f64)]) -> (Vector3<f64>, Vec<f64>) {
    const TOLERANCE: f64 = 1e-15;
    let mut p = *c;
    let mut mu = vec![0.0; planes.len()];
    let mut active: Vec<usize> = Vec::with_capacity(3);
    for _ in 0..4 * planes.len() + 8 {
        let slack = |j: usize| planes[j].0.dot(&p) - planes[j].1;
        let Some(s) =
            (0..planes.len()).filter(|&j| slack(j) < -TOLERANCE).min_by(|&i, &j| slack(i).total_cmp(&slack(j)))
        else {
            break;
        };
        let n = planes[s].0;
        // The step that keeps the active planes: z moves p, r trades their multipliers.
        let basis = nalgebra::DMatrix::from_fn(3, active.len(), |row, k| planes[active[k]].0[row]);
        let gram = basis.transpose() * &basis;
        let Some(inverse) = gram.try_inverse() else { break };
        let r = inverse * (basis.transpose() * nalgebra::DVector::from_column_slice(n.as_slice()));
        let z = n - Vector3::from_iterator((&basis * &r).iter().copied());
        let full = if z.norm_squared() > 1e-20 { -slack(s) / n.dot(&z) } else { f64::INFINITY };
        let blocking = (0..active.len())
            .filter(|&k| r[k] > 0.0)
            .map(|k| (mu[active[k]] / r[k], k))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let t = blocking.map_or(full, |(t, _)| t.min(full));
        if !t.is_finite() {
            break; // Opposing planes: no point is beyond all of them.
        }
        p += z * t;
        for (k, &j) in active.iter().enumerate() {
            mu[j] = (mu[j] - t * r[k]).max(0.0);
        }
        mu[s] += t;
        match blocking {
            Some((tb, k)) if tb < full => {
                mu[active[k]] = 0.0;
                active.remove(k);
            }
            _ => active.push(s),
        }
    }
    (p, mu)
}

/// The point of segment [a, b] nearest triangle (p, q, r), as its parameter on the segment,
/// and the distance (0 where the segment pierces the triangle).
pub fn segment_triangle_nearest(
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    p: &Vector3<f64>,
    q: &Vector3<f64>,
    r: &Vector3<f64>,
) -> (f64, f64) {
    let normal = (q - p).cross(&(r - p));
    let (da, db) = (normal.dot(&(a - p)), normal.dot(&(b - p)));
    if da * db <= 0.0 && da != db {
        let t = da / (da - db);
        let crossing = a + (b - a) * t;
        let (on, _) = closest_on_triangle(&crossing, p, q, r);
        if (on - crossing).norm() <= 1e-12 * (1.0 + crossing.norm()) {
            return (t, 0.0);
        }
    }
    let to_triangle = |t: f64| {
        let point = a + (b - a) * t;
        (t, (point - closest_on_triangle(&point, p, q, r).0).norm())
    };
    let edges = [(p, q), (q, r), (r, p)].map(|(u, v)| {
        let (t, s) = closest_between_segments(a, b, u, v);
        (t, ((a + (b - a) * t) - (u + (v - u) * s)).norm())
    });
    [to_triangle(0.0), to_triangle(1.0)]
        .into_iter()
        .chain(edges)
        .min_by(|g, h| g.1.total_cmp(&h.1).then(g.0.total_cmp(&h.0)))
        .unwrap_or((0.0, f64::INFINITY))
}

/// The parameters (s on [p1, q1], t on [p2, q2]) of the two segments' nearest points
/// (Ericson, *Real-Time Collision Detection*, 5.1.9).
fn closest_between_segments(p1: &Vector3<f64>, q1: &Vector3<f64>, p2: &Vector3<f64>, q2: &Vector3<f64>) -> (f64, f64) {
    let (d1, d2, r) = (q1 - p1, q2 - p2, p1 - p2);
    let (a, e, f) = (d1.norm_squared(), d2.norm_squared(), d2.dot(&r));
    if a <= f64::MIN_POSITIVE && e <= f64::MIN_POSITIVE {
        return (0.0, 0.0);
    }
    if a <= f64::MIN_POSITIVE {
        return (0.0, (f / e).clamp(0.0, 1.0));
    }
    let c = d1.dot(&r);
    if e <= f64::MIN_POSITIVE {
        return ((-c / a).clamp(0.0, 1.0), 0.0);
    }
    let b = d1.dot(&d2);
    let denom = a * e - b * b;
    let s = if denom > 0.0 { ((b * f - c * e) / denom).clamp(0.0, 1.0) } else { 0.0 };
    let t = (b * s + f) / e;
    if t < 0.0 {
        ((-c / a).clamp(0.0, 1.0), 0.0)
    } else if t > 1.0 {
        (((b - c) / a).clamp(0.0, 1.0), 1.0)
    } else {
        (s, t)
    }
}

/// The point of segment [a, b] nearest to p.
pub fn closest_on_segment(a: &Vector3<f64>, b: &Vector3<f64>, p: &Vector3<f64>) -> Vector3<f64> {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let t = if len2 > 0.0 { ((p - a).dot(&ab) / len2).clamp(0.0, 1.0) } else { 0.0 };
    a + ab * t
}

/// The point of triangle (a, b, c) nearest to p, and its barycentric weights (Ericson,
/// *Real-Time Collision Detection*, 5.1.5).
pub fn closest_on_triangle(
    p: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> (Vector3<f64>, [f64; 3]) {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return (*a, [1.0, 0.0, 0.0]);
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return (*b, [0.0, 1.0, 0.0]);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, [1.0 - v, v, 0.0]);
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return (*c, [0.0, 0.0, 1.0]);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, [1.0 - w, 0.0, w]);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, [0.0, 1.0 - w, w]);
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    (a + ab * v + ac * w, [1.0 - v - w, v, w])
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use defvol_core::mesh::generate::{self, CellSplit};

    /// The closest point is the minimiser of the distance: no point of a fine barycentric
    /// grid over the triangle is nearer.
    #[test]
    fn closest_point_on_a_triangle_is_nearer_than_every_grid_point() {
        let (a, b, c) = (Vector3::new(0.0, 0.0, 0.0), Vector3::new(1.0, 0.2, 0.0), Vector3::new(0.3, 0.9, 0.1));
        let probes = [
            Vector3::new(0.4, 0.3, 0.5),
            Vector3::new(-0.5, -0.2, 0.1),
            Vector3::new(1.5, 0.1, -0.3),
            Vector3::new(0.2, 1.4, 0.0),
            Vector3::new(0.8, 0.8, 0.2),
            Vector3::new(0.5, -0.4, 0.0),
        ];
        for p in probes {
            let (q, w) = closest_on_triangle(&p, &a, &b, &c);
            assert_relative_eq!(q, a * w[0] + b * w[1] + c * w[2], epsilon = 1e-12);
            assert_relative_eq!(w.iter().sum::<f64>(), 1.0, epsilon = 1e-12);
            let best = (0..=200)
                .flat_map(|i| (0..=200 - i).map(move |j| (i as f64 / 200.0, j as f64 / 200.0)))
                .map(|(v, w)| (p - (a + (b - a) * v + (c - a) * w)).norm())
                .fold(f64::INFINITY, f64::min);
            let d = (p - q).norm();
            assert!(d <= best + 1e-12 && d > best - 1e-2, "{p}: {d} vs grid {best}");
        }
    }

    fn slab() -> (defvol_core::mesh::TetMesh, Surface) {
        let mesh =
            generate::lattice(Vector3::new(0.0, 0.0, -0.06), Vector3::new(0.1, 0.1, 0.0), [6, 6, 4], CellSplit::Five)
                .unwrap();
        let surface = Surface::new(mesh.boundary(), mesh.nodes());
        (mesh, surface)
    }

    /// The hierarchy finds what a scan of every face finds.
    #[test]
    fn nearest_face_through_the_hierarchy_matches_a_scan_of_all_faces() {
        let (mesh, surface) = slab();
        let x = mesh.nodes();
        for (i, p) in
            [[0.031, 0.047, 0.003], [0.05, 0.05, -0.004], [0.099, 0.02, -0.03], [0.0, 0.0, 0.0]].into_iter().enumerate()
        {
            let p = Vector3::from(p);
            let tool = ToolCore { tool: i, core: ContactParams { a: p, b: p, radius: 0.006, stiffness: 1.0 } };
            let found = surface.detect(&[tool], x, 0.03);
            let scan = mesh
                .boundary()
                .iter()
                .map(|f| {
                    let [a, b, c] = f.map(|n| x[n as usize]);
                    (p - closest_on_triangle(&p, &a, &b, &c).0).norm()
                })
                .fold(f64::INFINITY, f64::min);
            let nearest = found.iter().map(|c| (p - c.at).norm()).fold(f64::INFINITY, f64::min);
            assert_relative_eq!(nearest, scan, epsilon = 1e-12);
            assert_eq!(surface.nearest_face(&p, x).map(|f| f.distance), Some(scan));
        }
    }

    /// The slab with its nodes pushed by a dent of `depth` under (0.05, 0.05, 0): a smooth
    /// field, largest at the top's middle.
    fn dented(mesh: &defvol_core::mesh::TetMesh, depth: f64) -> Vec<Vector3<f64>> {
        let centre = Vector3::new(0.05, 0.05, 0.0);
        (mesh.nodes().iter())
            .map(|p| p - Vector3::z() * depth * (-(p - centre).norm_squared() / (2.0 * 0.02f64.powi(2))).exp())
            .collect()
    }

    /// Between refits the hierarchy's boxes, grown by the drift, find every contact a
    /// hierarchy refitted to the moved nodes finds: the same contacts, bit for bit.
    #[test]
    fn drifted_boxes_find_what_refitted_boxes_find() {
        let (mesh, mut drifted) = slab();
        let depth = 0.4 * REFIT_DRIFT * drifted.spacing();
        let x = dented(&mesh, depth);
        drifted.moved(depth);
        drifted.keep_fitted(&x[..]);
        assert_eq!(drifted.drift, depth, "the move was small enough to keep the old boxes");
        let mut refitted = drifted.clone();
        refitted.refit(&x[..]);
        let mut found = 0;
        for (i, p) in [[0.05, 0.05, 0.0], [0.047, 0.052, -0.004], [0.06, 0.04, 0.002], [0.02, 0.08, -0.001]]
            .into_iter()
            .enumerate()
        {
            let p = Vector3::from(p);
            let tool = ToolCore { tool: i, core: ContactParams { a: p, b: p, radius: 0.002, stiffness: 1.0 } };
            let near = drifted.detect(&[tool], &x[..], 0.003);
            assert_eq!(near, refitted.detect(&[tool], &x[..], 0.003), "tool at {p}");
            found += near.len();
        }
        assert!(found >= 4, "the tools touch the dent: {found} contacts");
        for (i, j) in (0..21).flat_map(|i| (0..21).map(move |j| (i, j))) {
            let p = Vector3::new(0.03 + 0.002 * i as f64, 0.03 + 0.002 * j as f64, 0.0005 * (i + j) as f64 - 0.01);
            let (a, b) = (drifted.nearest_face(&p, &x[..]), refitted.nearest_face(&p, &x[..]));
            assert_eq!(a.map(|f| (f.face, f.distance)), b.map(|f| (f.face, f.distance)), "nearest to {p}");
        }
    }

    /// Inside or outside by the nearest feature's pseudo-normal agrees with the generalised
    /// winding number (the faces' solid angles over 4π; Jacobson et al. 2013), on a grid
    /// through a dented slab: inside, outside and just past the surface.
    #[test]
    fn inside_by_the_nearest_feature_agrees_with_the_winding_number() {
        let (mesh, mut surface) = slab();
        let x = dented(&mesh, 0.008);
        surface.refit(&x[..]);
        let winding = |p: &Vector3<f64>| {
            let solid_angle = |face: &[u32; 3]| {
                let [a, b, c] = face.map(|i| x[i as usize] - p);
                let (la, lb, lc) = (a.norm(), b.norm(), c.norm());
                let below = la * lb * lc + a.dot(&b) * lc + a.dot(&c) * lb + b.dot(&c) * la;
                2.0 * a.dot(&b.cross(&c)).atan2(below)
            };
            mesh.boundary().iter().map(solid_angle).sum::<f64>() / (4.0 * std::f64::consts::PI)
        };
        let mut inside = 0;
        for (i, j, k) in (0..13).flat_map(|i| (0..13).flat_map(move |j| (0..11).map(move |k| (i, j, k)))) {
            let p = Vector3::new(-0.006 + 0.0093 * i as f64, -0.004 + 0.0091 * j as f64, -0.066 + 0.0071 * k as f64);
            let w = winding(&p);
            assert!((w - 0.5).abs() > 0.1, "{p} lies on the surface (winding {w})");
            assert_eq!(surface.encloses(&p, &x[..]), w > 0.5, "{p}: winding {w}");
            inside += usize::from(w > 0.5);
        }
        assert!(inside > 300 && inside < 13 * 13 * 11 - 300, "{inside} of the grid inside");
    }

    /// A sample below the top face (inside the body) is pushed down past it, not up out of
    /// the far side: the pseudo-normal tells inside from outside.
    #[test]
    fn a_sample_past_the_surface_is_pushed_on_through() {
        let (mesh, surface) = slab();
        let tool = |z: f64| {
            let p = Vector3::new(0.043, 0.051, z);
            ToolCore { tool: 0, core: ContactParams { a: p, b: p, radius: 0.001, stiffness: 1.0 } }
        };
        let above = surface.detect(&[tool(0.0005)], mesh.nodes(), 0.0);
        let below = surface.detect(&[tool(-0.002)], mesh.nodes(), 0.0);
        assert_eq!((above.len(), below.len()), (1, 1));
        assert_relative_eq!(above[0].push, Vector3::new(0.0, 0.0, -1.0), epsilon = 1e-12);
        assert_relative_eq!(above[0].depth, 0.0005, epsilon = 1e-12);
        assert_relative_eq!(below[0].push, Vector3::new(0.0, 0.0, -1.0), epsilon = 1e-12);
        assert_relative_eq!(below[0].depth, 0.003, epsilon = 1e-12);
        assert!(surface.detect(&[tool(0.0011)], mesh.nodes(), 0.0).is_empty());
    }

    /// The projection beyond planes is optimal: its result meets the KKT conditions of
    /// min |p - c|² subject to n_j·p ≥ b_j (feasible, μ ≥ 0, p - c = Σ μ n, and μ_j > 0 only
    /// on planes p touches), which for this convex problem certify the minimiser; on sets
    /// with nearly parallel, redundant and corner planes.
    #[test]
    fn projection_beyond_planes_meets_the_optimality_conditions() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut random = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for case in 0..200 {
            let c = Vector3::new(random(), random(), random()) * 0.1;
            let count = 1 + case % 9;
            let planes: Vec<(Vector3<f64>, f64)> = (0..count)
                .map(|j| {
                    // Half the cases tilt every normal only slightly off +z: a shallow groove.
                    let spread = if case % 2 == 0 { 0.05 } else { 1.0 };
                    let n = (Vector3::z() + Vector3::new(random(), random(), random()) * spread).normalize();
                    let b = n.dot(&c) + 0.02 * random() + if j % 3 == 0 { 0.01 } else { 0.0 };
                    (n, b)
                })
                .collect();
            let (p, mu) = beyond_planes(&c, &planes);
            let mut sum = Vector3::zeros();
            for ((n, b), m) in planes.iter().zip(&mu) {
                let slack = n.dot(&p) - b;
                assert!(slack > -1e-12, "case {case}: a plane is violated by {slack}");
                assert!(*m >= 0.0 && m * slack.abs() < 1e-12, "case {case}: μ {m} on a plane {slack} away");
                sum += n * *m;
            }
            assert!((p - c - sum).norm() < 1e-12, "case {case}: p - c = {} but Σμn = {sum}", p - c);
        }
    }

    /// The segment's nearest point to a triangle is the minimiser over the segment: no point
    /// of a fine grid along it is nearer, crossing and parallel cases included.
    #[test]
    fn nearest_point_of_a_segment_to_a_triangle_beats_every_grid_point() {
        let (p, q, r) = (Vector3::new(0.0, 0.0, 0.0), Vector3::new(1.0, 0.2, 0.0), Vector3::new(0.3, 0.9, 0.1));
        let segments = [
            ([0.2, 0.2, 1.0], [0.3, 0.3, -1.0]), // pierces
            ([-1.0, -1.0, 0.5], [2.0, 2.0, 0.5]),
            ([2.0, 0.0, 0.3], [2.0, 1.0, -0.3]),
            ([-0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]), // a point
            ([0.0, -0.3, 0.0], [1.0, -0.1, 0.0]), // parallel to an edge, in the plane
            ([0.4, 0.4, 0.2], [0.6, 0.5, 0.25]),  // above the face
        ];
        for (a, b) in segments {
            let (a, b) = (Vector3::from(a), Vector3::from(b));
            let (t, distance) = segment_triangle_nearest(&a, &b, &p, &q, &r);
            let at = a + (b - a) * t;
            assert_relative_eq!(distance, (at - closest_on_triangle(&at, &p, &q, &r).0).norm(), epsilon = 1e-12);
            let best = (0..=10_000)
                .map(|k| a + (b - a) * (k as f64 / 10_000.0))
                .map(|s| (s - closest_on_triangle(&s, &p, &q, &r).0).norm())
                .fold(f64::INFINITY, f64::min);
            assert!(distance <= best + 1e-12 && distance > best - 1e-3, "{a} {b}: {distance} vs grid {best}");
        }
    }

    /// Two planes folded along the y axis, their far edges `half` either side in x at height
    /// `lift` (up: a groove, down: a ridge), `width` either side in y.
    fn fold(half: f64, lift: f64, width: f64) -> (Vec<Vector3<f64>>, [[u32; 3]; 4]) {
        let rest = vec![
            Vector3::new(0.0, -width, 0.0),
            Vector3::new(0.0, width, 0.0),
            Vector3::new(half, -width, lift),
            Vector3::new(half, width, lift),
            Vector3::new(-half, -width, lift),
            Vector3::new(-half, width, lift),
        ];
        (rest, [[0, 2, 3], [0, 3, 1], [0, 1, 5], [0, 5, 4]])
    }

    /// A needle slid along its axis across a steep ridge, from the ridge halfway between two
    /// samples to the ridge under one: at every position the ridge is pushed down as deep as
    /// the capsule reaches it, k (r - h) for its core h above the ridge, with no dip between
    /// samples (the samples' share and the gap sample's add up to it).
    #[test]
    fn a_needle_slid_over_a_ridge_is_pushed_as_deep_as_its_core_reaches_everywhere() {
        let (slope, half) = (1.2f64, 0.02);
        let (rest, faces) = fold(half, -half * slope.tan(), 0.05);
        let surface = Surface::new(&faces, &rest);
        let (radius, height, stiffness) = (0.001, 0.0004, 1000.0);
        let step = 0.5 * surface.spacing();
        assert!(0.5 * step > radius, "at first the ridge is out of every sample's reach");
        for k in 0..=40 {
            let from = -(2.5 * step) + step * k as f64 / 80.0;
            let (a, b) = (Vector3::new(from, 0.003, height), Vector3::new(from + 6.0 * step, 0.003, height));
            let tool = ToolCore { tool: 0, core: ContactParams { a, b, radius, stiffness } };
            let contacts = surface.detect(&[tool], &rest[..], 0.0);
            let down: f64 = contacts.iter().map(|c| c.force().z).sum();
            assert_relative_eq!(down, -stiffness * (radius - height), max_relative = 1e-9);
        }
    }

    /// A sphere resting in a V-groove is pushed out once, straight up, by as much as it
    /// must rise to clear both walls (r / cos θ - h for walls at θ, its centre h above the
    /// crease), not once per wall (which would push it about twice as hard).
    #[test]
    fn a_sphere_in_a_groove_is_pushed_out_once_not_once_per_wall() {
        let (theta, length) = (0.3f64, 1.0);
        let (rest, faces) = fold(length, length * theta.tan(), 1.0);
        let surface = Surface::new(&faces, &rest);
        let (radius, height, stiffness) = (0.2, 0.15, 1000.0);
        let centre = Vector3::new(0.0, 0.0, height);
        let tool = ToolCore { tool: 0, core: ContactParams { a: centre, b: centre, radius, stiffness } };
        let contacts = surface.detect(&[tool], &rest[..], 0.0);
        let force: Vector3<f64> = contacts.iter().map(|c| c.force()).sum();
        let on_nodes: Vector3<f64> = contacts.iter().flat_map(|c| c.node_forces()).map(|(_, f)| f).sum();
        let lift = radius / theta.cos() - height;
        assert_relative_eq!(force, Vector3::new(0.0, 0.0, -stiffness * lift), epsilon = 1e-9);
        assert_relative_eq!(on_nodes, force, epsilon = 1e-9);
    }

    /// Two tets glued along the edge (0, 1) only, and a third touching the first at node 3.
    fn touching() -> defvol_core::mesh::TetMesh {
        let n = vec![
            Vector3::zeros(),
            Vector3::x(),
            Vector3::y(),
            Vector3::z(),
            Vector3::new(0.0, -1.0, 0.0),
            Vector3::new(0.0, 0.0, -1.0),
            Vector3::new(0.0, 0.0, 2.0),
            Vector3::new(1.0, 0.0, 2.0),
            Vector3::new(0.0, 1.0, 2.0),
        ];
        let tets = vec![[0, 1, 2, 3], [0, 1, 4, 5], [3, 6, 7, 8]];
        defvol_core::mesh::TetMesh::new(n, tets, None, "touching").unwrap()
    }

    /// The tet whose boundary face `face` is.
    fn tet_of(mesh: &defvol_core::mesh::TetMesh, face: &[u32; 3]) -> usize {
        mesh.tets().iter().position(|t| face.iter().all(|n| t.contains(n))).unwrap()
    }

    /// Around the edge two bodies share, each face is paired with the face of its own body
    /// (the pair closes one wedge of material), never with the other body's.
    #[test]
    fn faces_at_an_edge_two_bodies_share_pair_within_each_body() {
        let mesh = touching();
        let surface = Surface::new(mesh.boundary(), mesh.nodes());
        let mut at_edge = 0;
        for (f, face) in mesh.boundary().iter().enumerate() {
            for k in 0..3 {
                let edge = [face[(k + 1) % 3], face[(k + 2) % 3]];
                if edge.contains(&0) && edge.contains(&1) {
                    at_edge += 1;
                    let partner = mesh.boundary()[surface.partners[f][k] as usize];
                    assert_ne!(partner, *face, "face {face:?} unpaired");
                    assert_eq!(tet_of(&mesh, &partner), tet_of(&mesh, face), "face {face:?} paired across bodies");
                }
            }
        }
        assert_eq!(at_edge, 4);
    }

    /// At a node two bodies share, each body's faces give that body's own normal there: it
    /// points out of that body, where the sum over both would not.
    #[test]
    fn a_node_two_bodies_share_has_a_normal_for_each() {
        let mesh = touching();
        let surface = Surface::new(mesh.boundary(), mesh.nodes());
        let x = mesh.nodes();
        let centroid = |t: usize| mesh.tets()[t].iter().map(|&n| x[n as usize]).sum::<Vector3<f64>>() / 4.0;
        let mut checked = 0;
        for (f, face) in mesh.boundary().iter().enumerate().filter(|(_, face)| face.contains(&3)) {
            let normal = surface.fan_normal(3, f as u32, x);
            let into_body = centroid(tet_of(&mesh, face)) - x[3];
            assert!(normal.dot(&into_body) < -0.3 * into_body.norm(), "face {face:?}: normal {normal}");
            checked += 1;
        }
        assert_eq!(checked, 6, "three faces of each body at node 3");
    }
}
