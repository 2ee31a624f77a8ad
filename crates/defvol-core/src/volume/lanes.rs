//! Trilinear samples at evenly spaced points along a line (a run of warp output voxels, a
//! ray's samples), eight at a time with AVX2 where the CPU has it (detected at run time;
//! elsewhere the caller's scalar loop does all of it). Each lane does the scalar loop's arithmetic in the same order: multiplies and adds
//! unfused, the same truncations and clamps, the corners read from the same cell; so
//! both give the same bits, and the f64 and GPU agreement tests hold the lanes as they hold
//! the scalar loop.

/// The source cell lookup both loops share: clamps keep every corner of a cell inside the
/// data, so the corner loads need no bounds test.
#[derive(Debug, Clone, Copy)]
pub struct CellLookup {
    /// The highest cell base index per axis (dims - 2, at least 0).
    pub top: [i32; 3],
    /// Steps to the +x, +y and +z corners (0 on an axis one voxel thick).
    pub strides: [i32; 3],
    /// Voxels in a row and in a slice.
    pub nx: i32,
    pub nxy: i32,
}

impl CellLookup {
    /// The lookup for x-fastest samples of `dims`.
    pub fn for_dims([nx, ny, nz]: [usize; 3]) -> Self {
        Self {
            top: [nx, ny, nz].map(|n| n.saturating_sub(2) as i32),
            strides: [usize::from(nx > 1), if ny > 1 { nx } else { 0 }, if nz > 1 { nx * ny } else { 0 }]
                .map(|s| s as i32),
            nx: nx as i32,
            nxy: (nx * ny) as i32,
        }
    }
}

/// Writes trilinear samples at `base + step·(start + n)` into `out` where AVX2 serves (a
/// last group of at most four takes four lanes; a last group's spare lanes sample points the
/// clamps keep inside the data, and only its own are stored); returns how many it wrote:
/// all of `out`, or none. `ahead`: the offset from this run to the one the caller samples
/// next, whose cells it asks the cache for as it goes (no effect on the samples).
pub fn trilinear_lanes(
    data: &[f32],
    cell: &CellLookup,
    out: &mut [f32],
    base: [f32; 3],
    step: [f32; 3],
    start: i32,
    ahead: Option<[f32; 3]>,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    if lanes_available() && x86::fits(data, cell) {
        // SAFETY: AVX2 is present, and every index the loads read is clamped to at most
        // the lookup's largest, which lies inside `data`.
        return unsafe { x86::trilinear_avx2(data, cell, out, base, step, start, ahead) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, cell, out, base, step, start, ahead);
    0
}

#[cfg(target_arch = "x86_64")]
pub use x86::Trilinear8;

/// Cells along a brick's edge: 2^BRICK_SHIFT.
const BRICK_SHIFT: i32 = 5;
const BRICK_CELLS: usize = 1 << BRICK_SHIFT;
/// Voxels along a brick's edge: its cells' far faces included.
const BRICK_EDGE: usize = BRICK_CELLS + 1;
const BRICK_VOXELS: usize = BRICK_EDGE * BRICK_EDGE * BRICK_EDGE;

/// The samples laid out in bricks of 32³ cells, each holding its cells' far faces too (33³
/// voxels; about 1.15x the samples with the last bricks' padding): a cell's eight corners
/// lie in one brick at fixed offsets, and points near in space are near in memory whatever
/// the direction between them. A rotated warp steps across rows and slices from voxel to
/// voxel, where row-major samples put each step on other cache lines and pages. 32³ cells
/// a brick beat 8³, 16³ and 64³ on the rotated warp (fewer brick crossings, less padding).
#[derive(Clone)]
pub struct Bricks {
    samples: BrickSamples,
    /// Bricks along x and y.
    bricks: [usize; 2],
    /// The highest cell index per axis (dims - 2, at least 0), as in [`CellLookup`].
    top: [i32; 3],
}

impl std::fmt::Debug for Bricks {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bricks").field("bricks", &self.bricks).field("samples", &self.samples.len()).finish()
    }
}

/// The bricks' samples: floats, or where every sample is q·2⁻ˢ for a 16-bit integer q
/// (CT numbers, s = 0; the phantom's eighths, s = 3), the q: half the memory and cache
/// lines, and read back exactly. The lanes lerp the q and scale the result by 2⁻ˢ, which
/// commutes with every rounding on the way: the floats' bits wherever the sample is a
/// normal float or zero.
#[derive(Clone)]
enum BrickSamples {
    Floats(Vec<f32>),
    Fixed { q: Vec<i16>, scale: f32 },
}

/// The most fraction bits a fixed-point sample may have.
const MAX_FRACTION_BITS: u32 = 15;

impl BrickSamples {
    /// Fixed point where every sample fits it exactly (-0.0 excluded: its sign would be lost), else floats.
    fn of(floats: Vec<f32>) -> Self {
        let bits = floats.iter().try_fold(0, |most, &v| fraction_bits(v).map(|b| b.max(most)));
        let scale = bits.filter(|&b| b <= MAX_FRACTION_BITS).map(|b| (1u32 << b) as f32);
        let fits = |scale: f32| floats.iter().all(|v| (v * scale).abs() <= i16::MAX as f32);
        match scale.filter(|&scale| fits(scale)) {
            Some(scale) => Self::Fixed { q: floats.iter().map(|v| (v * scale) as i16).collect(), scale: 1.0 / scale },
            None => Self::Floats(floats),
        }
    }

    fn len(&self) -> usize {
        match self {
            Self::Floats(v) => v.len(),
            Self::Fixed { q, .. } => q.len(),
        }
    }
}

/// The fraction bits `v` needs as a binary fixed-point number (0 for integers); None for
/// -0.0, infinities and NaN.
fn fraction_bits(v: f32) -> Option<u32> {
    if v == 0.0 {
        return v.is_sign_positive().then_some(0);
    }
    if !v.is_finite() {
        return None;
    }
    let bits = v.to_bits();
    let (exponent, mantissa) = ((bits >> 23 & 0xFF) as i32, bits & 0x7F_FFFF);
    // v = significand · 2^power, the significand an integer.
    let (significand, power) = match exponent {
        0 => (mantissa, -149),
        _ => (mantissa | 0x80_0000, exponent - 150),
    };
    Some((-(power + significand.trailing_zeros() as i32)).max(0) as u32)
}

impl Bricks {
    /// The bricked copy of x-fastest samples of `dims`, where the lanes can read it (AVX2
    /// present, its indices within i32); voxels past the far faces repeat the last one.
    pub fn new(data: &[f32], dims: [usize; 3]) -> Option<Self> {
        if !lanes_available() || data.len() != dims.iter().product::<usize>() {
            return None;
        }
        let count = dims.map(|n| n.saturating_sub(1).max(1).div_ceil(BRICK_CELLS));
        let len = count.iter().product::<usize>().checked_mul(BRICK_VOXELS)?;
        if len > i32::MAX as usize {
            return None;
        }
        let [nx, ny, nz] = dims;
        let mut bricked = vec![0f32; len];
        // One thread: a rayon worker building this inside `Volume::bricks` could steal a
        // task that asks for the same bricks, and wait on itself. A brick row at a time.
        for (brick, out) in bricked.chunks_exact_mut(BRICK_VOXELS).enumerate() {
            let [x0, y0, z0] =
                [brick % count[0], brick / count[0] % count[1], brick / (count[0] * count[1])].map(|b| b * BRICK_CELLS);
            for (r, dst) in out.chunks_exact_mut(BRICK_EDGE).enumerate() {
                // Voxels past the far faces repeat the last one.
                let (y, z) = ((y0 + r % BRICK_EDGE).min(ny - 1), (z0 + r / BRICK_EDGE).min(nz - 1));
                let row = &data[nx * (y + ny * z)..][..nx];
                match row.get(x0..x0 + BRICK_EDGE) {
                    Some(src) => dst.copy_from_slice(src),
                    None => dst.iter_mut().enumerate().for_each(|(l, v)| *v = row[(x0 + l).min(nx - 1)]),
                }
            }
        }
        Some(Self {
            samples: BrickSamples::of(bricked),
            bricks: [count[0], count[1]],
            top: dims.map(|n| n.saturating_sub(2) as i32),
        })
    }
}

/// Whether this CPU runs the eight-lane samplers.
pub fn lanes_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::arch::is_x86_feature_detected!("avx2");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// [`trilinear_lanes`] from bricked samples: the same cells, corners and arithmetic, so
/// the same bits.
pub fn trilinear_bricked(bricks: &Bricks, out: &mut [f32], base: [f32; 3], step: [f32; 3], start: i32) -> usize {
    #[cfg(target_arch = "x86_64")]
    if lanes_available() {
        // SAFETY: AVX2 is present; every bricked index lies in the bricks (clamped cells,
        // corners within their brick).
        return unsafe { x86::trilinear_bricked_avx2(bricks, out, base, step, start) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (bricks, out, base, step, start);
    0
}

/// Runs of samples along parallel lines (one step, each run on its own line), sampled from
/// bricks as one stream of eight-lane groups: a group takes the voxels of as many runs as
/// it reaches, so short runs (a tet's rows) fill every lane, and the loop runs long
/// instead of one or two groups and a set-up per run. Each voxel's point and sample are
/// those [`trilinear_bricked`] takes for its run: the same bits.
#[derive(Debug)]
pub struct RunStream {
    /// Per run: the index along its line of its first voxel, the line's base point, and
    /// where its samples go in the output.
    first: Vec<i32>,
    base: [Vec<f32>; 3],
    to: Vec<usize>,
    /// Where each run's samples begin in the stream, and one entry more: its length. Never
    /// empty (the first run begins at 0), so a push reads the last entry without a test.
    begin: Vec<i32>,
    samples: Vec<f32>,
}

impl Default for RunStream {
    fn default() -> Self {
        Self { first: Vec::new(), base: Default::default(), to: Vec::new(), begin: vec![0], samples: Vec::new() }
    }
}

impl RunStream {
    /// Empties the stream, keeping its memory.
    pub fn clear(&mut self) {
        self.first.clear();
        self.base.iter_mut().for_each(Vec::clear);
        self.to.clear();
        self.begin.truncate(1);
    }

    /// Adds runs l = 0..4 whose bit l of `kept` is set: run l's `len[l]` (≥ 1) voxels at
    /// `base[·][l] + step·(first[l] + n)`, written from `out[to[l]]`. Without a branch per
    /// run (four rows' spans, some of them empty, come straight from their lanes): all four
    /// are written and only the kept stay. How many voxels.
    #[inline]
    pub fn push4(&mut self, base: [[f32; 4]; 3], first: [i32; 4], len: [i32; 4], to: [usize; 4], kept: u32) -> u64 {
        let start = self.begin[self.begin.len() - 1];
        let (mut end, mut n) = (start, 0);
        let (mut firsts, mut bases, mut tos, mut ends) = ([0; 4], [[0.0; 4]; 3], [0; 4], [0; 4]);
        for l in 0..4 {
            let keep = (kept >> l & 1) as usize;
            firsts[n] = first[l];
            (0..3).for_each(|a| bases[a][n] = base[a][l]);
            tos[n] = to[l];
            end += len[l] & -(keep as i32);
            ends[n] = end;
            n += keep;
        }
        fn append<T: Copy>(v: &mut Vec<T>, four: [T; 4], n: usize) {
            let len = v.len();
            v.extend_from_slice(&four);
            v.truncate(len + n);
        }
        append(&mut self.first, firsts, n);
        (0..3).for_each(|a| append(&mut self.base[a], bases[a], n));
        append(&mut self.to, tos, n);
        append(&mut self.begin, ends, n);
        (end - start) as u64
    }

    /// Samples every run from `bricks` along `step` and writes each to its place in `out`;
    /// false (nothing written) where the CPU lacks the lanes.
    pub fn sample_into(&mut self, bricks: &Bricks, step: [f32; 3], out: &mut [f32]) -> bool {
        let runs = self.first.len();
        if runs == 0 {
            return true;
        }
        #[cfg(target_arch = "x86_64")]
        if lanes_available() {
            let total = self.begin[runs] as usize;
            // Padding: a group reads the entries of the eight runs from its first one;
            // lanes past the end take the last run's line (their samples are not written).
            for _ in 0..8 {
                self.first.push(self.first[runs - 1]);
                (0..3).for_each(|a| self.base[a].push(self.base[a][runs - 1]));
                self.begin.push(i32::MAX);
            }
            self.samples.resize(total.next_multiple_of(8), 0.0);
            // SAFETY: AVX2 is present; the entries are padded as the stream reads them.
            unsafe { x86::stream_bricked_avx2(bricks, self, step) };
            self.first.truncate(runs);
            self.base.iter_mut().for_each(|b| b.truncate(runs));
            self.begin.truncate(runs + 1);
            for (r, &to) in self.to.iter().enumerate() {
                let (from, end) = (self.begin[r] as usize, self.begin[r + 1] as usize);
                copy_run(&mut out[to..to + end - from], &self.samples[from..end]);
            }
            return true;
        }
        let _ = (bricks, step, out);
        false
    }
}

/// `to.copy_from_slice(from)` for the short runs of a stream: below 16 floats as two
/// fixed-size copies that overlap in the middle, inline instead of a call to `memcpy`.
#[inline]
fn copy_run(to: &mut [f32], from: &[f32]) {
    fn ends<const N: usize>(to: &mut [f32], from: &[f32]) {
        let n = to.len();
        to[..N].copy_from_slice(&from[..N]);
        to[n - N..].copy_from_slice(&from[n - N..]);
    }
    match to.len() {
        16.. => to.copy_from_slice(from),
        8.. => ends::<8>(to, from),
        4.. => ends::<4>(to, from),
        2.. => ends::<2>(to, from),
        _ => to.copy_from_slice(from),
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    // Named from the crate root, not `super`: the layer test reads `super` as the file's
    // parent module.
    use crate::volume::lanes::{
        BrickSamples, Bricks, CellLookup, RunStream, BRICK_CELLS, BRICK_EDGE, BRICK_SHIFT, BRICK_VOXELS,
    };
    use std::arch::x86_64::*;

    /// Whether `data` holds the largest index the clamps let a cell's corners reach, and
    /// the lanes' 32-bit offsets reach it without wrapping (worked out in 64 bits, so a
    /// lookup of any fields is judged right).
    pub(super) fn fits(data: &[f32], cell: &CellLookup) -> bool {
        let wide = |v: i32| i64::from(v);
        let max_offset = wide(cell.top[0])
            + wide(cell.nx) * wide(cell.top[1])
            + wide(cell.nxy) * wide(cell.top[2])
            + cell.strides.iter().map(|&s| wide(s)).sum::<i64>();
        (0..=wide(i32::MAX)).contains(&max_offset) && (max_offset as u64) < data.len() as u64
    }

    /// Where a cell's eight corners lie from its first, and the last first corner from
    /// which the samples hold eight floats past every corner.
    #[derive(Clone, Copy)]
    struct Corners {
        offsets: [isize; 8],
        reach: i32,
        /// Each even corner's +x neighbour is the next float (always in bricks; in rows
        /// more than one voxel long), so the two are read as a pair.
        paired: bool,
    }

    impl Corners {
        /// The corners at `offsets` (the last the farthest) in `len` samples.
        fn new(offsets: [isize; 8], len: usize) -> Self {
            let reach = (len as i64 - 8 - offsets[7] as i64).clamp(-1, i32::MAX as i64) as i32;
            let paired = (0..4).all(|p| offsets[2 * p + 1] == offsets[2 * p] + 1);
            Self { offsets, reach, paired }
        }
    }

    /// The cell lookup in vector lanes for row-major samples, set up once per run.
    #[derive(Clone, Copy)]
    struct Lanes {
        corners: Corners,
        nx: __m256i,
        nxy: __m256i,
        top: [__m256i; 3],
    }

    /// The cell lookup in vector lanes for bricked samples, set up once per run.
    struct BrickLanes {
        corners: Corners,
        top: [__m256i; 3],
        /// Per axis: a brick's step in samples, and a voxel's within the brick.
        brick_stride: [__m256i; 3],
        local_stride: [__m256i; 3],
        /// A cell's index within its brick: the low bits.
        low: __m256i,
    }

    /// A cell's first corner in row-major samples: i + nx·j + nxy·k.
    macro_rules! row_major_base {
        ($lanes:ident, $index:ident, $narrow:ident, $add_i:ident, $mullo:ident, $srli:ident, $and:ident) => {
            $add_i($add_i($index[0], $mullo($narrow($lanes.nx), $index[1])), $mullo($narrow($lanes.nxy), $index[2]))
        };
    }

    /// A cell's first corner in bricked samples: its brick's start plus its place in it.
    macro_rules! bricked_base {
        ($lanes:ident, $index:ident, $narrow:ident, $add_i:ident, $mullo:ident, $srli:ident, $and:ident) => {{
            let part = per_axis!(a => {
                let brick = $mullo($srli::<{ BRICK_SHIFT }>($index[a]), $narrow($lanes.brick_stride[a]));
                $add_i(brick, $mullo($and($index[a], $narrow($lanes.low)), $narrow($lanes.local_stride[a])))
            });
            $add_i($add_i(part[0], part[1]), part[2])
        }};
    }

    /// `[e(0), e(1), e(2)]`, written out: the samplers hold no closures, which LLVM may leave
    /// out of line once their function grows, spilling the lanes (see
    /// docs/perf/journal.md#samplers-written-out).
    macro_rules! per_axis {
        ($a:ident => $e:expr) => {
            [
                {
                    let $a = 0;
                    $e
                },
                {
                    let $a = 1;
                    $e
                },
                {
                    let $a = 2;
                    $e
                },
            ]
        };
    }

    /// The lanes of an `__m256i` as they are (the eight-lane samplers' narrowing).
    #[inline]
    fn same(v: __m256i) -> __m256i {
        v
    }

    /// Trilinear samples in one vector width: cell indices and fractions as the scalar loop
    /// takes them, the eight corners loaded (the cell's first corner found by `$base`,
    /// for the layout), then the seven lerps of `lerp_cube` in its order. Written once for
    /// eight lanes (ymm) and four (xmm), which a run's last few voxels take at half the
    /// loads.
    macro_rules! sample_fn {
        ($name:ident, $elem:ty, $base:ident, $ps:ty, $si:ty, $cvtt:ident, $cvt:ident, $max:ident, $min:ident,
         $add_i:ident, $mullo:ident, $srli:ident, $and:ident, $corners:ident, $add:ident, $sub:ident,
         $mul:ident, $zero:ident, $narrow:ident) => {
            /// # Safety
            /// The CPU must have AVX2, and `ptr` must lead the samples the lookup was made for.
            #[inline]
            #[target_feature(enable = "avx2")]
            unsafe fn $name(&self, ptr: *const $elem, at: [$ps; 3]) -> $ps {
                let zero = $zero();
                let index: [$si; 3] = per_axis!(a => $min($max($cvtt(at[a]), zero), $narrow(self.top[a])));
                let frac = per_axis!(a => $sub(at[a], $cvt(index[a])));
                let b = $base!(self, index, $narrow, $add_i, $mullo, $srli, $and);
                // b + corner is at most the lookup's largest index, inside the samples.
                let v = $corners!(ptr, b, self.corners);
                #[inline]
                #[target_feature(enable = "avx2")]
                fn lerp(a: $ps, b: $ps, f: $ps) -> $ps {
                    $add(a, $mul($sub(b, a), f))
                }
                let c00 = lerp(v[0], v[1], frac[0]);
                let c10 = lerp(v[2], v[3], frac[0]);
                let c01 = lerp(v[4], v[5], frac[0]);
                let c11 = lerp(v[6], v[7], frac[0]);
                lerp(lerp(c00, c10, frac[1]), lerp(c01, c11, frac[1]), frac[2])
            }
        };
    }

    /// The eight corners of `$width` cells (first corners `$b`, lane for lane) by scalar
    /// loads, cheaper than `vgatherdps` fetching the same floats (so the same bits). Macros,
    /// as is [`window!`]: as functions LLVM left them out of line, spilling the lanes (see
    /// docs/perf/journal.md#samplers-written-out).
    macro_rules! loads {
        ($ptr:ident, $b:ident, $corners:expr, $width:literal, $ps:ty, $store:ident, $set:ident, $($l:literal),+) => {{
            let mut index = [0i32; $width];
            // SAFETY: index holds $width i32.
            unsafe { $store(index.as_mut_ptr().cast(), $b) };
            let at = index.map(|i| $ptr.wrapping_offset(i as isize));
            let mut v: [$ps; 8] = [std::mem::zeroed(); 8];
            for (v, &c) in v.iter_mut().zip(&$corners.offsets) {
                // SAFETY: the caller's cells have their corners inside the samples.
                *v = unsafe { $set($(*at[$l].offset(c)),+) };
            }
            v
        }};
    }

    /// [`loads!`], but where the cells start within `$width` floats of lane 0's (a run
    /// along a row; a packet's neighbouring rays) a corner is one load of `$width` floats
    /// that each lane picks its own from.
    macro_rules! window {
        ($ptr:ident, $b:ident, $corners:expr, $width:literal, $ps:ty, $store:ident, $set:ident,
         $first:ident, $sub:ident, $set1:ident, $min_u:ident, $cmpeq:ident, $mask:ident, $all:literal,
         $loadu:ident, $permute:ident, $pack:ident, $shuffle:ident, $($l:literal),+) => {{
            let first = $first($b);
            let from_first = $sub($b, $set1(first));
            let within = $cmpeq($min_u(from_first, $set1($width - 1)), from_first);
            if $mask(within) == $all && first <= $corners.reach {
                // SAFETY: first + offset + width - 1 ≤ reach + offset + 7 < the samples' length.
                let at = unsafe { $ptr.offset(first as isize) };
                let mut v: [$ps; 8] = [std::mem::zeroed(); 8];
                for (v, &c) in v.iter_mut().zip(&$corners.offsets) {
                    // SAFETY: as above.
                    *v = $permute(unsafe { $loadu(at.offset(c)) }, from_first);
                }
                v
            } else if $corners.paired {
                pairs!($ptr, $b, $corners, $width, $ps, $store, $pack, $shuffle)
            } else {
                loads!($ptr, $b, $corners, $width, $ps, $store, $set, $($l),+)
            }
        }};
    }

    /// [`loads!`] for layouts where each even corner's +x neighbour is the next float
    /// ([`Corners::paired`]): a lane's two x-corners are one 8-byte load, two lanes' pairs
    /// fill one 128-bit half, and a shuffle splits the halves into the two corners' lanes.
    /// Half the loads and inserts of `loads!`, the same floats. `$pack` puts lanes (0, 1)
    /// and (2, 3) of each four in the first and second register, from vector loads: the
    /// same pairs built from 64-bit integers go through the stack (see
    /// docs/perf/journal.md#paired-corner-loads).
    macro_rules! pairs {
        ($ptr:ident, $b:ident, $corners:expr, $width:literal, $ps:ty, $store:ident, $pack:ident, $shuffle:ident) => {{
            let mut index = [0i32; $width];
            // SAFETY: index holds $width i32.
            unsafe { $store(index.as_mut_ptr().cast(), $b) };
            let mut v: [$ps; 8] = [std::mem::zeroed(); 8];
            for p in 0..4 {
                let c = $corners.offsets[2 * p];
                // SAFETY: corners c and c + 1 of every lane's cell lie inside the samples.
                let pair = index.map(|i| unsafe { _mm_loadl_epi64($ptr.offset(i as isize + c).cast()) });
                let (first, second) = $pack!(pair);
                v[2 * p] = $shuffle::<0x88>(first, second);
                v[2 * p + 1] = $shuffle::<0xDD>(first, second);
            }
            v
        }};
    }
    /// [`pairs!`] for fixed-point bricks: a lane's two x-corners are one 4-byte load of two
    /// i16, sign-extended into the two corners' lanes (the low half shifted up and back
    /// down, the high half down) and converted to floats, which hold them exactly.
    macro_rules! fixed_pairs {
        ($ptr:ident, $b:ident, $corners:expr, $width:literal, $ps:ty, $store:ident, $set:ident, $slli:ident,
         $srai:ident, $cvt:ident, $($l:literal),+) => {{
            let mut index = [0i32; $width];
            // SAFETY: index holds $width i32.
            unsafe { $store(index.as_mut_ptr().cast(), $b) };
            let mut v: [$ps; 8] = [std::mem::zeroed(); 8];
            for p in 0..4 {
                let c = $corners.offsets[2 * p];
                // SAFETY: corners c and c + 1 of every lane's cell lie inside the samples.
                let pair = $set($(unsafe { $ptr.offset(index[$l] as isize + c).cast::<i32>().read_unaligned() }),+);
                v[2 * p] = $cvt($srai::<16>($slli::<16>(pair)));
                v[2 * p + 1] = $cvt($srai::<16>(pair));
            }
            v
        }};
    }
    macro_rules! fixed_pairs8 {
        ($ptr:ident, $b:ident, $corners:expr) => {
            fixed_pairs!(
                $ptr,
                $b,
                $corners,
                8,
                __m256,
                _mm256_storeu_si256,
                _mm256_setr_epi32,
                _mm256_slli_epi32,
                _mm256_srai_epi32,
                _mm256_cvtepi32_ps,
                0,
                1,
                2,
                3,
                4,
                5,
                6,
                7
            )
        };
    }
    macro_rules! fixed_pairs4 {
        ($ptr:ident, $b:ident, $corners:expr) => {
            fixed_pairs!(
                $ptr,
                $b,
                $corners,
                4,
                __m128,
                _mm_storeu_si128,
                _mm_setr_epi32,
                _mm_slli_epi32,
                _mm_srai_epi32,
                _mm_cvtepi32_ps,
                0,
                1,
                2,
                3
            )
        };
    }
    macro_rules! pack8 {
        ($pair:ident) => {{
            let two = |a, b| _mm_unpacklo_epi64($pair[a], $pair[b]);
            (
                _mm256_castsi256_ps(_mm256_set_m128i(two(4, 5), two(0, 1))),
                _mm256_castsi256_ps(_mm256_set_m128i(two(6, 7), two(2, 3))),
            )
        }};
    }
    macro_rules! pack4 {
        ($pair:ident) => {
            (
                _mm_castsi128_ps(_mm_unpacklo_epi64($pair[0], $pair[1])),
                _mm_castsi128_ps(_mm_unpacklo_epi64($pair[2], $pair[3])),
            )
        };
    }

    /// The corner readers in eight lanes and in four.
    macro_rules! pairs8 {
        ($ptr:ident, $b:ident, $corners:expr) => {
            pairs!($ptr, $b, $corners, 8, __m256, _mm256_storeu_si256, pack8, _mm256_shuffle_ps)
        };
    }
    macro_rules! pairs4 {
        ($ptr:ident, $b:ident, $corners:expr) => {
            pairs!($ptr, $b, $corners, 4, __m128, _mm_storeu_si128, pack4, _mm_shuffle_ps)
        };
    }
    macro_rules! window8 {
        ($ptr:ident, $b:ident, $corners:expr) => {
            window!(
                $ptr,
                $b,
                $corners,
                8,
                __m256,
                _mm256_storeu_si256,
                _mm256_setr_ps,
                _mm256_cvtsi256_si32,
                _mm256_sub_epi32,
                _mm256_set1_epi32,
                _mm256_min_epu32,
                _mm256_cmpeq_epi32,
                _mm256_movemask_epi8,
                -1,
                _mm256_loadu_ps,
                _mm256_permutevar8x32_ps,
                pack8,
                _mm256_shuffle_ps,
                0,
                1,
                2,
                3,
                4,
                5,
                6,
                7
            )
        };
    }
    macro_rules! window4 {
        ($ptr:ident, $b:ident, $corners:expr) => {
            window!(
                $ptr,
                $b,
                $corners,
                4,
                __m128,
                _mm_storeu_si128,
                _mm_setr_ps,
                _mm_cvtsi128_si32,
                _mm_sub_epi32,
                _mm_set1_epi32,
                _mm_min_epu32,
                _mm_cmpeq_epi32,
                _mm_movemask_epi8,
                0xFFFF,
                _mm_loadu_ps,
                _mm_permutevar_ps,
                pack4,
                _mm_shuffle_ps,
                0,
                1,
                2,
                3
            )
        };
    }

    /// sample8 and sample4 for a layout, with its corner readers.
    macro_rules! sample_fns {
        ($s8:ident, $s4:ident, $elem:ty, $base:ident, $corners8:ident, $corners4:ident) => {
            sample_fn!(
                $s8,
                $elem,
                $base,
                __m256,
                __m256i,
                _mm256_cvttps_epi32,
                _mm256_cvtepi32_ps,
                _mm256_max_epi32,
                _mm256_min_epi32,
                _mm256_add_epi32,
                _mm256_mullo_epi32,
                _mm256_srli_epi32,
                _mm256_and_si256,
                $corners8,
                _mm256_add_ps,
                _mm256_sub_ps,
                _mm256_mul_ps,
                _mm256_setzero_si256,
                same
            );
            sample_fn!(
                $s4,
                $elem,
                $base,
                __m128,
                __m128i,
                _mm_cvttps_epi32,
                _mm_cvtepi32_ps,
                _mm_max_epi32,
                _mm_min_epi32,
                _mm_add_epi32,
                _mm_mullo_epi32,
                _mm_srli_epi32,
                _mm_and_si128,
                $corners4,
                _mm_add_ps,
                _mm_sub_ps,
                _mm_mul_ps,
                _mm_setzero_si128,
                _mm256_castsi256_si128
            );
        };
    }

    impl Lanes {
        #[inline]
        #[target_feature(enable = "avx2")]
        fn new(cell: &CellLookup, len: usize) -> Self {
            let [sx, sy, sz] = cell.strides.map(|s| s as isize);
            Self {
                corners: Corners::new([0, sx, sy, sy + sx, sz, sz + sx, sz + sy, sz + sy + sx], len),
                nx: _mm256_set1_epi32(cell.nx),
                nxy: _mm256_set1_epi32(cell.nxy),
                top: cell.top.map(|t| _mm256_set1_epi32(t)),
            }
        }

        // Rows: a run along them, or a packet's neighbouring rays, reads windows.
        sample_fns!(sample8, sample4, f32, row_major_base, window8, window4);

        /// Asks the cache for the corner rows of the cells of lanes 0 and 7 at `at` (a
        /// group's ends; the lanes between mostly share their lines). Any points: the cells
        /// are clamped as the samplers clamp them, and a prefetch reads nothing.
        #[inline]
        #[target_feature(enable = "avx2")]
        fn prefetch8(&self, ptr: *const f32, at: [__m256; 3]) {
            let zero = _mm256_setzero_si256();
            let index: [__m256i; 3] =
                per_axis!(a => _mm256_min_epi32(_mm256_max_epi32(_mm256_cvttps_epi32(at[a]), zero), self.top[a]));
            let b = row_major_base!(
                self,
                index,
                same,
                _mm256_add_epi32,
                _mm256_mullo_epi32,
                _mm256_srli_epi32,
                _mm256_and_si256
            );
            let mut cells = [0i32; 8];
            // SAFETY: cells holds eight i32.
            unsafe { _mm256_storeu_si256(cells.as_mut_ptr().cast(), b) };
            for cell in [cells[0], cells[7]] {
                for c in [0, 2, 4, 6] {
                    let at = ptr.wrapping_offset(cell as isize + self.corners.offsets[c]);
                    _mm_prefetch::<_MM_HINT_T0>(at.cast());
                }
            }
        }
    }

    impl BrickLanes {
        #[inline]
        #[target_feature(enable = "avx2")]
        fn new(bricks: &Bricks) -> Self {
            let [bx, by] = bricks.bricks.map(|b| b as i32);
            let (edge, slice) = (BRICK_EDGE as isize, (BRICK_EDGE * BRICK_EDGE) as isize);
            Self {
                corners: Corners::new(
                    [0, 1, edge, edge + 1, slice, slice + 1, slice + edge, slice + edge + 1],
                    bricks.samples.len(),
                ),
                top: bricks.top.map(|t| _mm256_set1_epi32(t)),
                brick_stride: [1, bx, bx * by].map(|s| _mm256_set1_epi32(s * BRICK_VOXELS as i32)),
                local_stride: [1, edge, slice].map(|s| _mm256_set1_epi32(s as i32)),
                low: _mm256_set1_epi32(BRICK_CELLS as i32 - 1),
            }
        }

        // Bricks serve runs across rows, where windows seldom hold; their corners always pair.
        sample_fns!(sample8, sample4, f32, bricked_base, pairs8, pairs4);
        sample_fns!(fixed8, fixed4, i16, bricked_base, fixed_pairs8, fixed_pairs4);
    }

    /// Trilinear samples at eight points of one vector: the row-major lanes with the samples
    /// they read, checked once to hold every index the clamps let a cell's corners reach.
    #[derive(Clone, Copy)]
    pub struct Trilinear8<'a> {
        lanes: Lanes,
        data: &'a [f32],
    }

    impl<'a> Trilinear8<'a> {
        /// The sampler for x-fastest `data` looked up by `cell`, where AVX2 serves and the
        /// data holds the lookup's largest index.
        pub fn new(data: &'a [f32], cell: &CellLookup) -> Option<Self> {
            if !crate::volume::lanes::lanes_available() || !fits(data, cell) {
                return None;
            }
            // SAFETY: AVX2 is present.
            Some(Self { lanes: unsafe { Lanes::new(cell, data.len()) }, data })
        }

        /// The samples at the eight points `at` (x, y, z lanes), each as the scalar loop
        /// takes it.
        ///
        /// # Safety
        /// The CPU must have AVX2 (a `Trilinear8` exists only where it does, so a caller
        /// holding one may call this).
        #[inline]
        #[target_feature(enable = "avx2")]
        pub fn sample(&self, at: [__m256; 3]) -> __m256 {
            // SAFETY: the data fits the lookup (checked in `new`); the clamps keep every
            // corner inside it.
            unsafe { self.lanes.sample8(self.data.as_ptr(), at) }
        }

        /// Asks the cache for the rows of the cells of lanes 0 and 7 at `at` (a packet's ends;
        /// the lanes between mostly share their lines), ahead of their samples. Any points:
        /// the cells are clamped as [`Self::sample`] clamps them, and a prefetch reads
        /// nothing.
        ///
        /// # Safety
        /// As [`Self::sample`]: a `Trilinear8` exists only where the CPU has AVX2.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub fn prefetch(&self, at: [__m256; 3]) {
            self.lanes.prefetch8(self.data.as_ptr(), at)
        }
    }

    /// Eight voxels a loop from bricked samples, as [`trilinear_avx2`].
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn trilinear_bricked_avx2(
        bricks: &Bricks,
        out: &mut [f32],
        base: [f32; 3],
        step: [f32; 3],
        start: i32,
    ) -> usize {
        let lanes = BrickLanes::new(bricks);
        // No prefetch: a rotated run's cells spread over more lines than a few prefetches
        // reach, and prefetching all eight lanes' bought nothing (side by side, rot45).
        let no_prefetch = None::<([f32; 3], fn([__m256; 3]))>;
        // SAFETY (both arms): every bricked index lies in the bricks (clamped cells,
        // corners within their brick).
        match &bricks.samples {
            BrickSamples::Floats(data) => {
                let ptr = data.as_ptr();
                let sample8 = |at| unsafe { lanes.sample8(ptr, at) };
                let sample4 = |at| unsafe { lanes.sample4(ptr, at) };
                run(out, [base, step], start, sample8, sample4, no_prefetch)
            }
            BrickSamples::Fixed { q, scale } => {
                let (ptr, scale8, scale4) = (q.as_ptr(), _mm256_set1_ps(*scale), _mm_set1_ps(*scale));
                let sample8 = |at| _mm256_mul_ps(unsafe { lanes.fixed8(ptr, at) }, scale8);
                let sample4 = |at| _mm_mul_ps(unsafe { lanes.fixed4(ptr, at) }, scale4);
                run(out, [base, step], start, sample8, sample4, no_prefetch)
            }
        }
    }

    /// [`RunStream::sample_into`]'s groups: each lane finds its run by counting the runs'
    /// beginnings it has passed, takes that run's line and index from a permute of the
    /// next eight runs' entries, and its point as the run's own loop computes it.
    ///
    /// # Safety
    /// The CPU must have AVX2; the stream's entries padded by eight past its last run, and
    /// its samples a whole number of groups long.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn stream_bricked_avx2(bricks: &Bricks, stream: &mut RunStream, step: [f32; 3]) {
        let lanes = BrickLanes::new(bricks);
        // SAFETY (both arms): every bricked index lies in the bricks (clamped cells,
        // corners within their brick).
        match &bricks.samples {
            BrickSamples::Floats(data) => stream_groups(stream, step, |at| unsafe { lanes.sample8(data.as_ptr(), at) }),
            BrickSamples::Fixed { q, scale } => {
                let scale = _mm256_set1_ps(*scale);
                stream_groups(stream, step, |at| _mm256_mul_ps(unsafe { lanes.fixed8(q.as_ptr(), at) }, scale))
            }
        }
    }

    /// The stream's groups, each lane's point found as [`stream_bricked_avx2`] says and
    /// sampled by `sample8`.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn stream_groups(stream: &mut RunStream, step: [f32; 3], sample8: impl Fn([__m256; 3]) -> __m256) {
        let RunStream { first, base, begin, samples, .. } = stream;
        let iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let step8 = step.map(|s| _mm256_set1_ps(s));
        let mut r = 0;
        for (g, group) in (0..).step_by(8).zip(samples.chunks_exact_mut(8)) {
            while begin[r + 1] <= g {
                r += 1;
            }
            let voxel = _mm256_add_epi32(_mm256_set1_epi32(g), iota);
            let mut which = _mm256_setzero_si256();
            let mut next = r + 1;
            while begin[next] < g + 8 {
                let passed = _mm256_cmpgt_epi32(voxel, _mm256_set1_epi32(begin[next] - 1));
                which = _mm256_sub_epi32(which, passed);
                next += 1;
            }
            // SAFETY: every entry list holds eight entries from r (padded).
            let pick =
                |v: &[i32]| _mm256_permutevar8x32_epi32(unsafe { _mm256_loadu_si256(v[r..].as_ptr().cast()) }, which);
            let pick_ps = |v: &[f32]| _mm256_permutevar8x32_ps(unsafe { _mm256_loadu_ps(v[r..].as_ptr()) }, which);
            let index = _mm256_add_epi32(pick(first), _mm256_sub_epi32(voxel, pick(begin)));
            let fi = _mm256_cvtepi32_ps(index);
            let at = per_axis!(a => _mm256_add_ps(pick_ps(&base[a]), _mm256_mul_ps(step8[a], fi)));
            // SAFETY: group holds eight floats.
            unsafe { _mm256_storeu_ps(group.as_mut_ptr(), sample8(at)) };
        }
    }

    /// The eight points `base + step·(first + l)`, lane l, multiplied and added unfused as
    /// the scalar loop does.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn along8(base: [__m256; 3], step: [__m256; 3], first: i32) -> [__m256; 3] {
        let iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let fi = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(first), iota));
        [0, 1, 2].map(|a| _mm256_add_ps(base[a], _mm256_mul_ps(step[a], fi)))
    }

    /// Stores the first `out.len()` lanes of `value`, at most eight.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn store8(out: &mut [f32], value: __m256) {
        let dst = out.as_mut_ptr();
        if out.len() >= 8 {
            // SAFETY: out holds eight floats.
            unsafe { _mm256_storeu_ps(dst, value) };
        } else {
            let iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let mask = _mm256_cmpgt_epi32(_mm256_set1_epi32(out.len() as i32), iota);
            // SAFETY: the mask writes only the floats out holds.
            unsafe { _mm256_maskstore_ps(dst, mask, value) };
        }
    }

    /// Eight voxels a loop at `base + step·(start + n)`, from row-major samples.
    ///
    /// # Safety
    /// The CPU must have AVX2, and `data` must [`fits`] the lookup.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn trilinear_avx2(
        data: &[f32],
        cell: &CellLookup,
        out: &mut [f32],
        base: [f32; 3],
        step: [f32; 3],
        start: i32,
        ahead: Option<[f32; 3]>,
    ) -> usize {
        let (lanes, ptr) = (Lanes::new(cell, data.len()), data.as_ptr());
        // SAFETY: the caller's data fits the lookup.
        let sample8 = |at| unsafe { lanes.sample8(ptr, at) };
        let sample4 = |at| unsafe { lanes.sample4(ptr, at) };
        run(out, [base, step], start, sample8, sample4, ahead.map(|ahead| (ahead, |at| lanes.prefetch8(ptr, at))))
    }

    /// The samples at `base + step·(start + n)` into `out`, eight lanes a loop; a last group
    /// of at most four takes four lanes, and a last group stores only its own voxels.
    /// With `ahead` (an offset and a prefetcher), each group also asks the cache for the
    /// cells of the run that far away: the one the caller samples next, whose first cells
    /// a short run would otherwise wait for. Returns `out.len()`.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn run(
        out: &mut [f32],
        [base, step]: [[f32; 3]; 2],
        start: i32,
        sample8: impl Fn([__m256; 3]) -> __m256,
        sample4: impl Fn([__m128; 3]) -> __m128,
        ahead: Option<([f32; 3], impl Fn([__m256; 3]))>,
    ) -> usize {
        let len = out.len();
        let iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let base8 = base.map(|b| _mm256_set1_ps(b));
        let step8 = step.map(|s| _mm256_set1_ps(s));
        let mut n = 0;
        while len - n > 4 {
            if let Some((offset, prefetch8)) = &ahead {
                let later = per_axis!(a => _mm256_set1_ps(base[a] + offset[a]));
                prefetch8(along8(later, step8, start + n as i32));
            }
            store8(&mut out[n..], sample8(along8(base8, step8, start + n as i32)));
            n = (n + 8).min(len);
        }
        if n < len {
            let iota = _mm256_castsi256_si128(iota);
            let fi = _mm_cvtepi32_ps(_mm_add_epi32(_mm_set1_epi32(start + n as i32), iota));
            let at = [0, 1, 2].map(|a| _mm_add_ps(_mm_set1_ps(base[a]), _mm_mul_ps(_mm_set1_ps(step[a]), fi)));
            let value = sample4(at);
            let mask = _mm_cmpgt_epi32(_mm_set1_epi32((len - n) as i32), iota);
            // SAFETY: the mask writes only the len - n ≤ 4 floats out holds from n.
            unsafe { _mm_maskstore_ps(out[n..].as_mut_ptr(), mask, value) };
        }
        len
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::{lerp_cube, trilinear};

    /// The scalar loop's arithmetic for one voxel, as the warp's `Sampler::trilinear_run` does it.
    fn scalar(data: &[f32], cell: &CellLookup, base: [f32; 3], step: [f32; 3], n: i32) -> f32 {
        let fi = n as f32;
        let at = [0, 1, 2].map(|a| base[a] + step[a] * fi);
        let index = [0, 1, 2].map(|a| (at[a] as i32).clamp(0, cell.top[a]));
        let b = (index[0] + cell.nx * index[1] + cell.nxy * index[2]) as usize;
        let [sx, sy, sz] = cell.strides.map(|s| s as usize);
        lerp_cube(|o| data[b + o], [sx, sy, sz], [0, 1, 2].map(|a| at[a] - index[a] as f32))
    }

    /// Runs of every length from 1 to 19 through a 7x5x4 source, at points inside it and
    /// within round-off of its faces: the lanes give the scalar loop's bits, and the f64
    /// trilinear sample to 1e-5 of the range.
    #[test]
    fn lanes_give_the_scalar_loops_bits_and_the_f64_sample() {
        let dims = [7usize, 5, 4];
        let data: Vec<f32> = (0..140).map(|v| ((v * 37) % 101) as f32 - 50.0).collect();
        let cell = CellLookup::for_dims(dims);
        assert_eq!((cell.top, cell.strides, cell.nx, cell.nxy), ([5, 3, 2], [1, 7, 35], 7, 35));
        let mut checked = 0;
        for len in 1..20usize {
            let start = (len % 3) as i32;
            // From near one corner towards the opposite one, staying inside the box.
            let base = [0.0f32, 4.0 - 1e-7, 0.25];
            let reach = (start + len as i32 - 1).max(1) as f32;
            let step = [6.0 / reach, -3.9 / reach, 2.7 / reach];
            let mut out = vec![f32::NAN; len];
            if trilinear_lanes(&data, &cell, &mut out, base, step, start, None) == 0 {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            }
            for (n, value) in out.iter().enumerate() {
                let expected = scalar(&data, &cell, base, step, start + n as i32);
                assert_eq!(value.to_bits(), expected.to_bits(), "run of {len}, voxel {n}");
                let fi = f64::from(start + n as i32);
                let at = [0, 1, 2].map(|a| f64::from(base[a]) + f64::from(step[a]) * fi);
                let reference = trilinear(&data, dims, at[0], at[1], at[2], 1e-3).unwrap();
                assert!((f64::from(*value) - reference).abs() < 1e-5 * 100.0, "{value} vs {reference}");
                checked += 1;
            }
        }
        assert_eq!(checked, 190);
    }

    /// Runs across a source one voxel wide, where a cell's corners have no +x neighbour to
    /// be read with in pairs and are read one by one, and across a source one voxel high,
    /// whose rows pair: both give the scalar loop's bits.
    #[test]
    fn corners_read_singly_or_in_pairs_give_the_scalar_loops_bits() {
        let mut checked = 0;
        for dims in [[1usize, 13, 11], [13, 1, 11]] {
            let Some((data, cell, _)) = varied_source(dims, 1.0) else {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            };
            let top = dims.map(|n| (n - 1) as f32);
            for run in 1..20usize {
                // Corner to corner: consecutive voxels a cell or more apart, no window holds.
                let step = top.map(|t| t / run as f32);
                let mut out = vec![f32::NAN; run];
                assert_eq!(trilinear_lanes(&data, &cell, &mut out, [0.0; 3], step, 1, None), run);
                checked += assert_scalar_bits(&out, (&data, &cell), [[0.0; 3], step], &format!("{dims:?}"));
            }
        }
        assert_eq!(checked, 2 * 190);
    }

    /// Asserts that a run's samples from n = 1 on are the scalar loop's bits; how many.
    fn assert_scalar_bits(
        out: &[f32],
        (data, cell): (&[f32], &CellLookup),
        [base, step]: [[f32; 3]; 2],
        what: &str,
    ) -> usize {
        for (n, value) in out.iter().enumerate() {
            let expected = scalar(data, cell, base, step, 1 + n as i32);
            assert_eq!(value.to_bits(), expected.to_bits(), "{what}, run of {}, voxel {n}", out.len());
        }
        out.len()
    }

    /// Samples of `dims` with varied values (integers -50..=50 times `unit`), their lookup
    /// and their bricks (none without AVX2).
    fn varied_source(dims: [usize; 3], unit: f32) -> Option<(Vec<f32>, CellLookup, Bricks)> {
        let len = dims.iter().product::<usize>();
        let data: Vec<f32> = (0..len).map(|v| (((v * 37) % 101) as f32 - 50.0) * unit).collect();
        let bricks = Bricks::new(&data, dims)?;
        Some((data, CellLookup::for_dims(dims), bricks))
    }

    /// Runs along rows (0.3-1 voxel a step in x, forwards and back, a little across), where
    /// a group's cells lie within eight floats of its first cell's and the corners are read
    /// a window at a time, up to the samples' last floats, and in sources too small for a
    /// window: both layouts give the row-major scalar loop's bits.
    #[test]
    fn runs_along_rows_give_the_scalar_loops_bits() {
        let mut checked = 0;
        for dims in [[29usize, 6, 5], [9, 2, 2], [5, 1, 1]] {
            let Some((data, cell, bricks)) = varied_source(dims, 1.0) else {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            };
            let far = dims.map(|n| (n - 1) as f32);
            for across in [[0.0, 0.0], [far[1] - 0.25, far[2]], [0.5, far[2] * 0.5]] {
                for dx in [0.3f32, 0.5, 1.0, -0.5, -1.0] {
                    for run in 1..24usize {
                        // Each run ends on the source's far x face (forwards) or starts there.
                        let reach = dx.abs() * run as f32;
                        let x0 = if dx > 0.0 { (far[0] - reach).max(0.0) } else { far[0] };
                        let step = [dx, 1e-3, -1e-3];
                        let base = [x0 - dx, across[0], across[1]];
                        let mut rows = vec![f32::NAN; run];
                        let mut bricked = vec![f32::NAN; run];
                        assert_eq!(trilinear_lanes(&data, &cell, &mut rows, base, step, 1, Some([0.0, 2.0, 0.0])), run);
                        assert_eq!(trilinear_bricked(&bricks, &mut bricked, base, step, 1), run);
                        for n in 0..run {
                            let expected = scalar(&data, &cell, base, step, 1 + n as i32).to_bits();
                            assert_eq!(rows[n].to_bits(), expected, "{dims:?} {dx} run of {run}, voxel {n}");
                            assert_eq!(bricked[n].to_bits(), expected, "bricked {dims:?} {dx} run of {run}, voxel {n}");
                            checked += 1;
                        }
                    }
                }
            }
        }
        assert_eq!(checked, 3 * 3 * 5 * 276);
    }

    /// Runs in tilted directions through sources of several bricks a side, one of them
    /// one voxel thick along y, from points on brick faces and within round-off of the
    /// source's faces: the bricked lanes give the row-major scalar loop's bits.
    /// Both brick layouts: integers and eighths in 16-bit fixed point, tenths as floats.
    #[test]
    fn bricked_lanes_give_the_scalar_loops_bits() {
        let mut checked = 0;
        for (dims, unit) in [[70usize, 35, 34], [66, 1, 40]].into_iter().flat_map(|d| [1.0, 0.125, 0.1].map(|u| (d, u)))
        {
            let Some((data, cell, bricks)) = varied_source(dims, unit) else {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            };
            assert_eq!(matches!(bricks.samples, BrickSamples::Fixed { .. }), unit != 0.1, "unit {unit}");
            let top = dims.map(|n| (n - 1) as f32);
            for (base, end) in [
                ([0.0, 0.0, 0.0], top),
                ([top[0], BRICK_CELLS as f32, 0.0], [0.0, 0.0, top[2]]),
                ([BRICK_CELLS as f32, top[1] - 1e-6, BRICK_CELLS as f32], [2.0 * BRICK_CELLS as f32 + 1e-6, 0.0, 0.5]),
            ] {
                for run in 1..24usize {
                    let step = [0, 1, 2].map(|a| (end[a] - base[a]) / run as f32);
                    let mut out = vec![f32::NAN; run];
                    assert_eq!(trilinear_bricked(&bricks, &mut out, base, step, 1), run);
                    checked += assert_scalar_bits(&out, (&data, &cell), [base, step], &format!("{dims:?}"));
                }
            }
        }
        assert_eq!(checked, 2 * 3 * 3 * 276);
    }

    /// Runs of 1-19 voxels on lines through the source (tilted, from brick faces and
    /// within round-off of its faces), sampled as one stream, give each run's own
    /// bricked samples bit for bit, in both layouts, and write nothing between runs.
    #[test]
    fn a_stream_of_runs_gives_each_runs_own_samples() {
        for unit in [0.125, 0.1] {
            let Some((_, _, bricks)) = varied_source([70, 40, 45], unit) else {
                eprintln!("skipped: no AVX2 on this CPU");
                return;
            };
            let step = [0.61, 0.37, -0.29];
            let (mut stream, mut expected, mut to) = (RunStream::default(), vec![f32::NAN; 4000], 0);
            // Runs 4·four..4·four + 4 go in together, the first of each four and others kept.
            let kept_of = |four: usize| ((four as u32 * 7) % 16) | 1;
            for four in 0..50usize {
                let kept = kept_of(four);
                let (mut base, mut first, mut len, mut at) = ([[0.0; 4]; 3], [0; 4], [0; 4], [0; 4]);
                for l in 0..4 {
                    let r = 4 * four + l;
                    let b = [(r % 3) as f32 * 12.0 + 8.0, (r % 11) as f32 * 3.0 - 1e-6, 44.0 - (r % 7) as f32 * 2.0];
                    (0..3).for_each(|a| base[a][l] = b[a]);
                    (first[l], len[l], at[l]) = ((r % 5) as i32, 1 + (r * 7 % 19) as i32, to);
                    if kept >> l & 1 == 1 {
                        let out = &mut expected[to..to + len[l] as usize];
                        assert_eq!(trilinear_bricked(&bricks, out, b, step, first[l]), out.len());
                        to += len[l] as usize + r % 3;
                    }
                }
                stream.push4(base, first, len, at, kept);
            }
            let mut out = vec![f32::NAN; 4000];
            assert!(stream.sample_into(&bricks, step, &mut out));
            for (n, (got, want)) in out.iter().zip(&expected).enumerate() {
                assert_eq!(got.to_bits(), want.to_bits(), "unit {unit}, voxel {n}");
            }
            let gaps = (0..200).filter(|r| kept_of(r / 4) >> (r % 4) & 1 == 1).map(|r| r % 3).sum();
            assert!(to > 1000 && expected[..to].iter().filter(|v| v.is_nan()).count() == gaps);
        }
    }

    /// Four runs pushed at once keep exactly the runs their mask keeps, in order, each
    /// run's samples beginning where the kept runs before it end, for every mask of four.
    #[test]
    fn four_runs_pushed_at_once_are_exactly_the_kept_ones() {
        let (mut stream, mut kept_runs) = (RunStream::default(), Vec::new());
        for kept in 0..16u32 {
            let k = kept as i32;
            let base = [0, 1, 2].map(|a| [0, 1, 2, 3].map(|l| (k * 10 + l * 3 + a) as f32 * 0.5));
            let (first, len) = ([0, 1, 2, 3].map(|l| k - l), [0, 1, 2, 3].map(|l| 1 + (k + l) % 5));
            let to = [0, 1, 2, 3].map(|l| (k * 100 + l * 20) as usize);
            let runs: Vec<usize> = (0..4).filter(|l| kept >> l & 1 == 1).collect();
            let voxels = runs.iter().map(|&l| len[l] as u64).sum();
            assert_eq!(stream.push4(base, first, len, to, kept), voxels);
            kept_runs.extend(runs.iter().map(|&l| (base.map(|b| b[l]), first[l], len[l], to[l])));
        }
        assert_eq!(kept_runs.len(), 32);
        let ends = kept_runs.iter().scan(0, |end, run| Some(std::mem::replace(end, *end + run.2)));
        for (r, ((base, first, len, to), begin)) in kept_runs.iter().zip(ends).enumerate() {
            let entry = ([0, 1, 2].map(|a| stream.base[a][r]), stream.first[r], stream.begin[r + 1] - stream.begin[r]);
            assert_eq!((entry, stream.to[r], stream.begin[r]), ((*base, *first, *len), *to, begin), "run {r}");
        }
        assert_eq!((stream.first.len(), stream.begin.len()), (32, 33));
    }

    /// Samples are held in 16 bits exactly when each is q·2⁻ˢ with |q| ≤ 32767 and
    /// s ≤ 15: CT numbers and eighths are, tenths, -0.0, NaN and 40000 are not.
    #[test]
    fn sixteen_bits_hold_exactly_the_samples_they_can() {
        assert_eq!([3.0, 0.5, -0.375, 0.0, 2f32.powi(-149)].map(fraction_bits), [0, 1, 3, 0, 149].map(Some));
        assert_eq!([-0.0, f32::NAN, f32::INFINITY].map(fraction_bits), [None; 3]);
        let fixed = |v: Vec<f32>| match BrickSamples::of(v) {
            BrickSamples::Fixed { q, scale } => Some((q, scale)),
            BrickSamples::Floats(_) => None,
        };
        assert_eq!(fixed(vec![-1024.0, 3071.0, 0.0]), Some((vec![-1024, 3071, 0], 1.0)));
        assert_eq!(fixed(vec![-1000.0, 12.375]), Some((vec![-8000, 99], 0.125)));
        assert_eq!(fixed(vec![32767.0, -32767.0]), Some((vec![32767, -32767], 1.0)));
        for floats in [vec![0.1], vec![-0.0, 1.0], vec![40000.0], vec![-32767.0, 0.5], vec![2f32.powi(-16)]] {
            assert_eq!(fixed(floats.clone()), None, "{floats:?}");
        }
    }

    /// A lookup fits data that holds its farthest corner and no less; one whose 32-bit
    /// offsets would wrap (here to 4, within eight samples) fits nothing.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn a_lookup_fits_only_data_holding_its_farthest_corner_unwrapped() {
        let cell = CellLookup::for_dims([7, 5, 4]);
        assert!(x86::fits(&[0.0; 140], &cell) && !x86::fits(&[0.0; 139], &cell));
        let wrapping = CellLookup { top: [0, 0, 4], strides: [0; 3], nx: 1, nxy: (1 << 30) + 1 };
        assert_eq!(wrapping.nxy.wrapping_mul(wrapping.top[2]), 4);
        assert!(!x86::fits(&[0.0; 8], &wrapping));
    }
}
