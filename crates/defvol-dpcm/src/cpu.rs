//! The CPU path: rayon over bands of rows, each phyxel stepped by `kernels.rs`, the line-by-line
//! twin of `dpcm.wgsl`.

use std::collections::HashMap;

use rayon::prelude::*;

use crate::config::{DpcmConfig, Marker};
use crate::error::DpcmError;
use crate::kernels::{self, Coeffs, FixedRest, KernelMarker, PlasticRest, Rows, UniformRest, TILE};
use crate::texture::{load_texture, TexturedParameter};

/// What a step did with its markers.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StepStats {
    pub markers_applied: usize,
    /// Markers with a NaN or infinite coordinate, or invalid parameters: dropped.
    pub markers_dropped: usize,
    /// Markers whose reach lies wholly outside the grid.
    pub markers_off_grid: usize,
}

/// Markers binned into tiles (CSR): the lists both paths read.
#[derive(Debug, Default, Clone)]
pub struct MarkerBins {
    pub markers: Vec<KernelMarker>,
    pub tiles_x: usize,
    pub tiles_y: usize,
    /// Tile t's markers are `indices[offsets[t]..offsets[t + 1]]`.
    pub offsets: Vec<u32>,
    pub indices: Vec<u32>,
}

impl MarkerBins {
    fn tile_range(m: &KernelMarker, width: usize, height: usize) -> Option<([usize; 2], [usize; 2])> {
        let lo_x = (m.col - m.threshold).floor().max(0.0);
        let hi_x = (m.col + m.threshold).ceil().min(width as f32 - 1.0);
        let lo_y = (m.row - m.threshold).floor().max(0.0);
        let hi_y = (m.row + m.threshold).ceil().min(height as f32 - 1.0);
        if lo_x > hi_x || lo_y > hi_y {
            return None;
        }
        Some(([lo_x as usize / TILE, hi_x as usize / TILE], [lo_y as usize / TILE, hi_y as usize / TILE]))
    }

    /// Bins `markers` for a `width` x `height` grid; returns how many reach no phyxel.
    pub fn build(&mut self, markers: Vec<KernelMarker>, width: usize, height: usize) -> usize {
        self.tiles_x = width.div_ceil(TILE);
        self.tiles_y = height.div_ceil(TILE);
        let tiles = self.tiles_x * self.tiles_y;
        self.offsets.clear();
        self.offsets.resize(tiles + 1, 0);
        let mut off_grid = 0;
        let ranges: Vec<_> = markers.iter().map(|m| Self::tile_range(m, width, height)).collect();
        for range in &ranges {
            let Some(([x0, x1], [y0, y1])) = *range else {
                off_grid += 1;
                continue;
            };
            for ty in y0..=y1 {
                for tx in x0..=x1 {
                    self.offsets[ty * self.tiles_x + tx + 1] += 1;
                }
            }
        }
        for t in 0..tiles {
            self.offsets[t + 1] += self.offsets[t];
        }
        self.indices.clear();
        self.indices.resize(self.offsets[tiles] as usize, 0);
        let mut fill: Vec<u32> = self.offsets[..tiles].to_vec();
        for (index, range) in ranges.iter().enumerate() {
            let Some(([x0, x1], [y0, y1])) = *range else { continue };
            for ty in y0..=y1 {
                for tx in x0..=x1 {
                    let t = ty * self.tiles_x + tx;
                    self.indices[fill[t] as usize] = index as u32;
                    fill[t] += 1;
                }
            }
        }
        self.markers = markers;
        off_grid
    }

    pub fn tile(&self, tx: usize, ty: usize) -> &[u32] {
        let t = ty * self.tiles_x + tx;
        &self.indices[self.offsets[t] as usize..self.offsets[t + 1] as usize]
    }
}

/// Ground coefficients per phyxel, when a texture sets them.
#[derive(Debug, Clone)]
struct GroundTexture {
    a: Vec<f32>,
    b: Vec<f32>,
}

/// A DPCM grid and its state, stepped on the CPU.
#[derive(Debug, Clone)]
pub struct Surface {
    config: DpcmConfig,
    coeffs: Coeffs,
    /// The configured rest height L0; the state below is relative to it.
    rest_height: f32,
    /// u(n) = Z(n) - L0, u(n-1), and the buffer u(n+1) is written to.
    u: Vec<f32>,
    up: Vec<f32>,
    next: Vec<f32>,
    /// Per-phyxel ground rest points (minus L0): plastic ground or a rest-height texture.
    /// Empty: every rest point at L0.
    rest: Vec<f32>,
    initial_rest: Vec<f32>,
    ground: Option<GroundTexture>,
    /// Per-phyxel link masks of a stochastic topology (empty: every link exists).
    links: Vec<u8>,
    marker_heights: HashMap<u32, f32>,
    bins: MarkerBins,
    steps: u64,
}

/// Rows per rayon task: a multiple of the tile side, so tiles never straddle two tasks.
const BAND_ROWS: usize = 4 * TILE;

impl Surface {
    pub fn new(config: &DpcmConfig) -> Result<Self, DpcmError> {
        let coeffs = config.coeffs()?;
        let n = config.width * config.height;
        let rest_height = config.rest_height as f32;
        let mut rest = Vec::new();
        let mut ground = None;
        for texture in &config.textures {
            let values = load_texture(texture, config.width, config.height)?;
            match texture.parameter {
                TexturedParameter::RestHeight => rest = values.iter().map(|r| r - rest_height).collect(),
                TexturedParameter::GroundStiffness | TexturedParameter::GroundDamping => {
                    let g = ground.get_or_insert_with(|| GroundTexture {
                        a: vec![coeffs.ground_a; n],
                        b: vec![coeffs.ground_b; n],
                    });
                    let (target, base) = if texture.parameter == TexturedParameter::GroundStiffness {
                        (&mut g.a, config.ground.stiffness() * config.dt * config.dt / config.mass)
                    } else {
                        (&mut g.b, config.ground.damping() * config.dt / config.mass)
                    };
                    for (t, v) in target.iter_mut().zip(&values) {
                        *t = (base * f64::from(*v)) as f32;
                    }
                }
            }
        }
        if rest.is_empty() && coeffs.plastic_threshold >= 0.0 {
            rest = vec![0.0; n];
        }
        let u = if rest.is_empty() { vec![0.0; n] } else { rest.clone() };
        Ok(Self {
            config: config.clone(),
            coeffs,
            rest_height,
            up: u.clone(),
            next: u.clone(),
            u,
            initial_rest: rest.clone(),
            rest,
            ground,
            links: if coeffs.link_keep < 1 << 24 {
                kernels::link_masks(&coeffs, config.width, config.height)
            } else {
                Vec::new()
            },
            marker_heights: HashMap::new(),
            bins: MarkerBins::default(),
            steps: 0,
        })
    }

    pub fn config(&self) -> &DpcmConfig {
        &self.config
    }
    pub fn coeffs(&self) -> &Coeffs {
        &self.coeffs
    }
    pub fn width(&self) -> usize {
        self.config.width
    }
    pub fn height(&self) -> usize {
        self.config.height
    }
    pub fn steps(&self) -> u64 {
        self.steps
    }
    /// The configured rest height L0.
    pub fn rest_height(&self) -> f32 {
        self.rest_height
    }
    /// u(n) = Z(n) - L0, row-major (x fastest): the state the kernels step.
    pub fn deviations(&self) -> &[f32] {
        &self.u
    }
    /// u(n-1).
    pub fn previous_deviations(&self) -> &[f32] {
        &self.up
    }
    /// Z(n), metres.
    pub fn heights(&self) -> Vec<f32> {
        self.u.iter().map(|u| u + self.rest_height).collect()
    }
    /// Z(n-1).
    pub fn previous_heights(&self) -> Vec<f32> {
        self.up.iter().map(|u| u + self.rest_height).collect()
    }
    /// The ground links' rest points minus L0 (moved by plasticity); empty when all are 0.
    pub fn rest_deviations(&self) -> &[f32] {
        &self.rest
    }
    /// The ground links' rest points now, metres.
    pub fn rest_heights(&self) -> Vec<f32> {
        if self.rest.is_empty() {
            vec![self.rest_height; self.u.len()]
        } else {
            self.rest.iter().map(|r| r + self.rest_height).collect()
        }
    }
    /// Ground coefficients of phyxel i: (k·h²/m, c·h/m).
    pub fn ground_coeffs(&self, i: usize) -> (f32, f32) {
        match &self.ground {
            Some(g) => (g.a[i], g.b[i]),
            None => (self.coeffs.ground_a, self.coeffs.ground_b),
        }
    }
    /// Z minus the initial rest point: the engraving, as rendered.
    pub fn displacement(&self) -> Vec<f32> {
        if self.initial_rest.is_empty() {
            self.u.clone()
        } else {
            self.u.iter().zip(&self.initial_rest).map(|(u, r)| u - r).collect()
        }
    }

    /// Sets Z(n) = Z(n-1) = `heights` (a disturbance released at rest).
    pub fn set_heights(&mut self, heights: &[f32]) -> Result<(), DpcmError> {
        if heights.len() != self.u.len() || heights.iter().any(|h| !h.is_finite()) {
            return Err(DpcmError::BadParameter {
                name: "heights".into(),
                value: heights.len() as f64,
                why: format!("need {} finite values", self.u.len()),
            });
        }
        for ((u, up), h) in self.u.iter_mut().zip(&mut self.up).zip(heights) {
            *u = h - self.rest_height;
            *up = *u;
        }
        Ok(())
    }

    /// Back to the initial balance state (seed 004, section 4.2.4).
    pub fn reset(&mut self) {
        self.rest.clone_from(&self.initial_rest);
        let u = if self.rest.is_empty() { vec![0.0; self.u.len()] } else { self.rest.clone() };
        self.up.copy_from_slice(&u);
        self.u = u;
        self.marker_heights.clear();
        self.steps = 0;
    }

    /// Markers as the kernels read them, binned; NaN markers and bad parameters dropped.
    pub fn bin_markers(&mut self, markers: &[Marker]) -> StepStats {
        let (kernel_markers, mut stats) = to_kernel_markers(&self.config, &mut self.marker_heights, markers);
        stats.markers_off_grid = self.bins.build(kernel_markers, self.config.width, self.config.height);
        stats.markers_applied -= stats.markers_off_grid;
        stats
    }

    pub fn bins(&self) -> &MarkerBins {
        &self.bins
    }

    /// One Verlet step under `markers`.
    pub fn step(&mut self, markers: &[Marker]) -> StepStats {
        let stats = self.bin_markers(markers);
        self.step_binned();
        stats
    }

    /// One step with the markers already binned (the benchmark and the GPU twin share bins).
    pub fn step_binned(&mut self) {
        let (w, h) = (self.config.width, self.config.height);
        let band = BAND_ROWS * w;
        let bands = h.div_ceil(BAND_ROWS);
        let rest_bands: Vec<&mut [f32]> = if self.rest.is_empty() {
            std::iter::repeat_with(|| &mut [][..]).take(bands).collect()
        } else {
            self.rest.chunks_mut(band).collect()
        };
        let plastic = self.coeffs.plastic_threshold >= 0.0;
        let links = (!self.links.is_empty()).then_some(&self.links[..]);
        let ctx = StepContext {
            c: &self.coeffs,
            u: &self.u,
            up: &self.up,
            width: w,
            height: h,
            ground: self.ground.as_ref(),
            plastic,
            links,
            bins: &self.bins,
        };
        self.next
            .par_chunks_mut(band)
            .zip(rest_bands)
            .enumerate()
            .for_each(|(b, (out, rest))| step_band(&ctx, b * BAND_ROWS, out, rest));
        std::mem::swap(&mut self.up, &mut self.u);
        std::mem::swap(&mut self.u, &mut self.next);
        self.steps += 1;
    }
}

/// Converts and validates markers; tracks each marker's last height for its velocity.
pub fn to_kernel_markers(
    config: &DpcmConfig,
    last_heights: &mut HashMap<u32, f32>,
    markers: &[Marker],
) -> (Vec<KernelMarker>, StepStats) {
    let mut stats = StepStats::default();
    let mut out = Vec::with_capacity(markers.len());
    let (h, m, s) = (config.dt, config.mass, config.spacing);
    let mut seen = HashMap::with_capacity(markers.len());
    for marker in markers {
        let params = marker.params.unwrap_or(config.marker);
        let finite = marker.col.is_finite() && marker.row.is_finite() && marker.height.is_finite();
        if !finite
            || params.validate("marker").is_err()
            || params.stiffness > config.marker.stiffness
            || params.damping > config.marker.damping
        {
            // Stiffer markers than the configured one could break the checked stability bound.
            stats.markers_dropped += 1;
            continue;
        }
        let height = (marker.height - config.rest_height) as f32;
        let step_dz = last_heights.get(&marker.id).map_or(0.0, |last| height - last);
        seen.insert(marker.id, height);
        out.push(KernelMarker {
            col: marker.col as f32,
            row: marker.row as f32,
            height,
            step_dz,
            stiffness_a: (params.stiffness * h * h / m * s) as f32,
            damping_b: (params.damping * h / m) as f32,
            threshold: (params.threshold / s) as f32,
            z_scale: (1.0 / ((1.0 - params.flattening) * s)) as f32,
        });
    }
    *last_heights = seen;
    stats.markers_applied = out.len();
    (out, stats)
}

/// One band, compiled for AVX2 (8 lanes) where the CPU has it and dispatched at run time.
/// Rust never fuses multiply-adds on its own, so every version gives the same bits.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+avx"))]
fn step_band(ctx: &StepContext, y0: usize, out: &mut [f32], rest: &mut [f32]) {
    ctx.band(y0, out, rest);
}

/// What a band task reads.
struct StepContext<'a> {
    c: &'a Coeffs,
    u: &'a [f32],
    up: &'a [f32],
    width: usize,
    height: usize,
    ground: Option<&'a GroundTexture>,
    plastic: bool,
    /// The stochastic topology's link masks; `None`: every link.
    links: Option<&'a [u8]>,
    bins: &'a MarkerBins,
}

impl StepContext<'_> {
    /// Rows y0.. of Z(n+1) into `out` (whole rows), then the markers of the band's tiles.
    #[inline(always)]
    fn band(&self, y0: usize, out: &mut [f32], rest: &mut [f32]) {
        let w = self.width;
        let rows = out.len() / w;
        for dy in 0..rows {
            let y = y0 + dy;
            let out_row = &mut out[dy * w..(dy + 1) * w];
            let rest_row: &mut [f32] = if rest.is_empty() { &mut [] } else { &mut rest[dy * w..(dy + 1) * w] };
            if y > 0 && y + 1 < self.height {
                self.interior(y, out_row, rest_row);
                for x in [0, w - 1] {
                    self.general(x, y, out_row, rest_row);
                }
            } else {
                for x in 0..w {
                    self.general(x, y, out_row, rest_row);
                }
            }
        }
        self.markers(y0, rows, out);
    }

    #[inline(always)]
    fn general(&self, x: usize, y: usize, out_row: &mut [f32], rest_row: &mut [f32]) {
        let i = y * self.width + x;
        let rest = if rest_row.is_empty() {
            0.0
        } else {
            let r = if self.plastic { kernels::plastic_rest(self.c, rest_row[x], self.u[i]) } else { rest_row[x] };
            rest_row[x] = r;
            r
        };
        let (ga, gb) = match self.ground {
            Some(g) => (g.a[i], g.b[i]),
            None => (self.c.ground_a, self.c.ground_b),
        };
        out_row[x] = kernels::phyxel_update(self.c, ga, gb, rest, self.u, self.up, self.width, self.height, x, y);
    }

    #[inline(always)]
    fn interior<'a>(&'a self, y: usize, out: &mut [f32], rest: &mut [f32]) {
        let w = self.width;
        let row = |v: &'a [f32], y: usize| -> &'a [f32] { &v[y * w..(y + 1) * w] };
        let rows = Rows {
            up: row(self.u, y - 1),
            mid: row(self.u, y),
            down: row(self.u, y + 1),
            up_p: row(self.up, y - 1),
            mid_p: row(self.up, y),
            down_p: row(self.up, y + 1),
        };
        let links = self.links.map(|l| &l[y * w..(y + 1) * w]);
        match (self.c.has_axial != 0, self.c.has_diagonal != 0, links) {
            (false, false, _) => self.interior_kinds::<false, false, _>(kernels::AllLinks, y, &rows, out, rest),
            (true, false, None) => self.interior_kinds::<true, false, _>(kernels::AllLinks, y, &rows, out, rest),
            (false, true, None) => self.interior_kinds::<false, true, _>(kernels::AllLinks, y, &rows, out, rest),
            (true, true, None) => self.interior_kinds::<true, true, _>(kernels::AllLinks, y, &rows, out, rest),
            (true, false, Some(m)) => self.interior_kinds::<true, false, _>(m, y, &rows, out, rest),
            (false, true, Some(m)) => self.interior_kinds::<false, true, _>(m, y, &rows, out, rest),
            (true, true, Some(m)) => self.interior_kinds::<true, true, _>(m, y, &rows, out, rest),
        }
    }

    /// One instantiation per ground texture and rest kind: no branch inside the row.
    #[inline(always)]
    fn interior_kinds<const AX: bool, const DG: bool, M: kernels::LinkMask>(
        &self,
        links: M,
        y: usize,
        rows: &Rows,
        out: &mut [f32],
        rest: &mut [f32],
    ) {
        let c = self.c;
        let w = self.width;
        match (self.ground, rest.is_empty(), self.plastic) {
            (None, true, _) => kernels::interior_row::<AX, DG, _, _, _, _>(
                c,
                links,
                c.ground_a,
                c.ground_b,
                UniformRest(0.0),
                rows,
                out,
            ),
            (None, false, false) => kernels::interior_row::<AX, DG, _, _, _, _>(
                c,
                links,
                c.ground_a,
                c.ground_b,
                FixedRest(rest),
                rows,
                out,
            ),
            (None, false, true) => kernels::interior_row::<AX, DG, _, _, _, _>(
                c,
                links,
                c.ground_a,
                c.ground_b,
                PlasticRest(rest),
                rows,
                out,
            ),
            (Some(g), true, _) => kernels::interior_row::<AX, DG, _, _, _, _>(
                c,
                links,
                &g.a[y * w..(y + 1) * w],
                &g.b[y * w..(y + 1) * w],
                UniformRest(0.0),
                rows,
                out,
            ),
            (Some(g), false, false) => kernels::interior_row::<AX, DG, _, _, _, _>(
                c,
                links,
                &g.a[y * w..(y + 1) * w],
                &g.b[y * w..(y + 1) * w],
                FixedRest(rest),
                rows,
                out,
            ),
            (Some(g), false, true) => kernels::interior_row::<AX, DG, _, _, _, _>(
                c,
                links,
                &g.a[y * w..(y + 1) * w],
                &g.b[y * w..(y + 1) * w],
                PlasticRest(rest),
                rows,
                out,
            ),
        }
    }

    /// Adds the markers' pushes to the band's phyxels, tile by tile (as the GPU gathers them).
    #[inline(always)]
    fn markers(&self, y0: usize, rows: usize, out: &mut [f32]) {
        if self.bins.markers.is_empty() {
            return;
        }
        let w = self.width;
        let mut push = [0.0f32; TILE * TILE];
        for ty in y0 / TILE..(y0 + rows).div_ceil(TILE) {
            let (row0, row1) = (ty * TILE, ((ty + 1) * TILE).min(y0 + rows));
            for tx in 0..self.bins.tiles_x {
                let list = self.bins.tile(tx, ty);
                if list.is_empty() {
                    continue;
                }
                let (col0, col1) = (tx * TILE, ((tx + 1) * TILE).min(w));
                // Marker by marker over its own box: each phyxel still sums its markers in
                // list order (as the GPU does); phyxels out of a marker's reach would add 0.
                let span = |m: &KernelMarker, centre: f32, lo: usize, hi: usize| {
                    (
                        (centre - m.threshold).floor().max(lo as f32) as usize,
                        ((centre + m.threshold).ceil() + 1.0).clamp(lo as f32, hi as f32) as usize,
                    )
                };
                let (mut bx, mut by) = ((col1, col0), (row1, row0));
                for &m in list {
                    let m = &self.bins.markers[m as usize];
                    let ((xa, xb), (ya, yb)) = (span(m, m.col, col0, col1), span(m, m.row, row0, row1));
                    (bx, by) = ((bx.0.min(xa), bx.1.max(xb)), (by.0.min(ya), by.1.max(yb)));
                }
                if bx.0 >= bx.1 {
                    continue;
                }
                for y in by.0..by.1 {
                    push[(y - row0) * TILE + (bx.0 - col0)..(y - row0) * TILE + (bx.1 - col0)].fill(0.0);
                }
                for &m in list {
                    let m = &self.bins.markers[m as usize];
                    let ((xa, xb), (ya, yb)) = (span(m, m.col, col0, col1), span(m, m.row, row0, row1));
                    if xa >= xb {
                        continue;
                    }
                    for y in ya..yb {
                        let (u, up) = (&self.u[y * w + xa..y * w + xb], &self.up[y * w + xa..y * w + xb]);
                        let row = &mut push[(y - row0) * TILE + (xa - col0)..(y - row0) * TILE + (xb - col0)];
                        for (k, ((p, &u), &up)) in row.iter_mut().zip(u).zip(up).enumerate() {
                            *p += kernels::marker_term(m, (xa + k) as f32, y as f32, u, u - up);
                        }
                    }
                }
                for y in by.0..by.1 {
                    for x in bx.0..bx.1 {
                        out[(y - y0) * w + x] += push[(y - row0) * TILE + (x - col0)];
                    }
                }
            }
        }
    }
}
