//! The CPU path: output slices in parallel (rayon), each rasterized by `kernels.rs` from
//! the tets that overlap it, in tet order; the displacement-only warp; and the incremental
//! warp that redoes only the region the mesh moved in.

use std::sync::Arc;

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::kernels::{initial_value, rasterize_slab, tet_maps, Sampler, TetMap};
use crate::{WarpError, WarpOptions, WarpPath, WarpStats};
use defvol_core::math::Real;
use defvol_core::mesh::TetMesh;
use defvol_core::volume::{Grid, Volume};

/// The default output grid: the deformed nodes' box at the source's spacing and direction,
/// snapped to the source lattice (so an identity warp is a plain copy).
pub fn default_grid(source: &Volume, deformed: &[Vector3<f64>]) -> Grid {
    let g = source.grid();
    let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
    for p in deformed {
        let ijk = g.index_from_world(*p);
        lo = lo.inf(&ijk);
        hi = hi.sup(&ijk);
    }
    let lo = lo.map(|v| (v - 1e-9).ceil());
    let hi = hi.map(|v| (v + 1e-9).floor());
    // Saturating: nodes thrown far off (a runaway deformation) give a box the size check
    // refuses, not a count that wraps.
    let dims = [0, 1, 2].map(|a| ((hi[a] - lo[a]).max(0.0) as usize).saturating_add(1));
    Grid { dims, spacing: g.spacing, origin: g.world_from_index(lo).into(), direction: g.direction }
}

/// Output slices a task rasterizes together: as many as fit in this many bytes (a slab
/// stays in a core's cache from its fill to its last tet, and each tet's source footprint
/// is read once for all its slices in the slab), at least one: a core's L2 (see
/// docs/perf/journal.md#warp-slabs).
const SLAB_BYTES: usize = 1 << 20;

/// [`SLAB_BYTES`] for a re-warped region: a local press has a few slabs to share between
/// the threads, which thinner ones balance (see docs/perf/journal.md#warp-slabs).
const REGION_SLAB_BYTES: usize = 1 << 19;

fn slab_depth<T>(nx: usize, ny: usize, path: WarpPath, bytes: usize) -> usize {
    match path {
        WarpPath::Fast => (bytes / (nx * ny * std::mem::size_of::<T>())).max(1),
        WarpPath::Scalar => 1,
    }
}

/// Which tets overlap each slab of `depth` slices from `first` to `last`, in tet order.
fn slab_bins(maps: &[Option<TetMap>], first: usize, last: usize, depth: usize) -> Vec<Vec<u32>> {
    let mut bins = vec![Vec::new(); (last - first) / depth + 1];
    for (t, m) in maps.iter().enumerate() {
        let Some(m) = m else { continue };
        if m.hi[2] < first || m.lo[2] > last {
            continue;
        }
        let (s0, s1) = ((m.lo[2].max(first) - first) / depth, (m.hi[2].min(last) - first) / depth);
        for bin in &mut bins[s0..=s1] {
            bin.push(t as u32);
        }
    }
    bins
}

/// Sets every sample of `out` to `value`. f32 samples are stored by `rep stosd` on x86-64:
/// the CPU's fast-string stores write whole cache lines without reading them first, where a
/// loop of vector stores reads each line of the (uncached) output before overwriting it
/// (see docs/perf/journal.md#background-by-fast-string-stores).
fn fill<T: Real>(out: &mut [T], value: f32) {
    match T::as_f32_mut(out) {
        #[cfg(target_arch = "x86_64")]
        Some(samples) => {
            // SAFETY: `rep stosd` writes rcx = samples.len() 32-bit values from rdi, the
            // start of the slice, forwards (the ABI keeps the direction flag clear), and
            // touches no flags and no stack.
            unsafe {
                std::arch::asm!(
                    "rep stosd",
                    inout("rcx") samples.len() => _,
                    inout("rdi") samples.as_mut_ptr() => _,
                    in("eax") value.to_bits(),
                    options(nostack, preserves_flags),
                );
            }
        }
        _ => out.fill(T::of(value as f64)),
    }
}

fn check_size(grid: &Grid, bytes_per_voxel: u64, options: &WarpOptions) -> Result<(), WarpError> {
    // Without wrapping: a runaway deformation's box can hold more bytes than 64 bits count
    // (`Grid::len` saturates; said as 2^64 bytes in MiB, as the GPU path says it).
    let needed = (grid.len() as u64).checked_mul(bytes_per_voxel);
    match needed {
        Some(needed) if needed <= options.max_bytes => Ok(()),
        _ => Err(WarpError::TooLarge {
            dims: grid.dims,
            needed_mib: needed.unwrap_or(u64::MAX).div_ceil(1 << 20),
            limit_mib: options.max_bytes >> 20,
        }),
    }
}

/// Warps `source` through `rest` → `deformed` onto `grid`, in precision T (f32: the fast
/// path; f64: the reference). Positions are in the source's physical units.
pub fn warp_samples<T: Real>(
    source: &Volume,
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    grid: &Grid,
    options: &WarpOptions,
) -> Result<(Vec<T>, WarpStats), WarpError> {
    check_size(grid, std::mem::size_of::<T>() as u64, options)?;
    let mut out = vec![T::zero(); grid.len()];
    let stats = warp_into(source, rest, deformed, grid, options, &mut out)?;
    Ok((out, stats))
}

/// As [`warp_samples`], into a caller's buffer of `grid.len()` samples (reused from frame
/// to frame, or a shared-memory sample being published).
pub fn warp_into<T: Real>(
    source: &Volume,
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    grid: &Grid,
    options: &WarpOptions,
    out: &mut [T],
) -> Result<WarpStats, WarpError> {
    check_size(grid, std::mem::size_of::<T>() as u64, options)?;
    if out.len() != grid.len() {
        return Err(WarpError::BufferSize { got: out.len(), expected: grid.len() });
    }
    let maps = tet_maps(rest, deformed, &source.grid(), grid)?;
    let sampler = Sampler::new(source, options)?;
    let identity = grid.index_map_to(&source.grid());
    let [nx, ny, nz] = grid.dims;
    let depth = slab_depth::<T>(nx, ny, options.path, SLAB_BYTES);
    let bins = slab_bins(&maps, 0, nz - 1, depth);
    let mut stats = out
        .par_chunks_mut(nx * ny * depth)
        .enumerate()
        .map(|(s, slab)| {
            let k0 = s * depth;
            if options.keep_uncovered {
                for (dk, slice) in slab.chunks_mut(nx * ny).enumerate() {
                    for j in 0..ny {
                        for i in 0..nx {
                            slice[i + nx * j] = initial_value(&sampler, &identity, true, i, j, k0 + dk);
                        }
                    }
                }
            } else {
                fill(slab, options.background);
            }
            rasterize_slab(slab, [nx, ny], k0, &bins[s], &maps, &sampler, options.scheme, [0, 0], [nx - 1, ny - 1])
        })
        .reduce(WarpStats::default, |mut a, b| {
            a += b;
            a
        });
    stats.voxels = grid.len() as u64;
    stats.skipped_tets = maps.iter().filter(|m| m.is_none()).count() as u64;
    Ok(stats)
}

/// The f32 warp as a volume on `grid`.
pub fn warp(
    source: &Volume,
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    grid: &Grid,
    options: &WarpOptions,
) -> Result<(Volume, WarpStats), WarpError> {
    let (data, stats) = warp_samples::<f32>(source, rest, deformed, grid, options)?;
    Ok((Volume::from_grid(grid, data, "warped volume")?, stats))
}

/// Displacement volumes alone (no mesh): out(p) = src(backward(p)) on `grid`.
pub fn displace(source: &Volume, grid: &Grid, options: &WarpOptions) -> Result<Volume, WarpError> {
    check_size(grid, 4, options)?;
    let sampler = Sampler::new(source, options)?;
    let identity = grid.index_map_to(&source.grid());
    let [nx, ny, _] = grid.dims;
    let mut out = vec![0f32; grid.len()];
    out.par_chunks_mut(nx * ny).enumerate().for_each(|(k, slice)| {
        for j in 0..ny {
            for i in 0..nx {
                slice[i + nx * j] = initial_value(&sampler, &identity, true, i, j, k);
            }
        }
    });
    Ok(Volume::from_grid(grid, out, "displaced volume")?)
}

/// A box of output voxels, inclusive.
type Region = ([usize; 3], [usize; 3]);

/// Advances whose moved regions are remembered: a buffer that held a warp up to this many
/// advances ago is brought up to date region by region, an older one whole.
const HISTORY: usize = 64;

/// A warp kept up to date as the mesh moves, written wherever its consumer wants it.
///
/// [`IncrementalWarp::advance`] takes new deformed positions and notes the region of the
/// tets with a node that moved more than `tolerance`; [`IncrementalWarp::write_into`] then
/// brings any buffer to the current warp: one that holds an earlier warp of this sequence
/// (its owner says which) is re-warped only inside the regions moved since, any other is
/// warped whole. A rotating set of shared-memory samples is therefore written in place,
/// each only where the volume changed since it last went out, and never copied.
pub struct IncrementalWarp {
    source: Arc<Volume>,
    rest: Arc<TetMesh>,
    grid: Grid,
    options: WarpOptions,
    positions: Vec<Vector3<f64>>,
    maps: Vec<Option<TetMap>>,
    /// Advances so far: the warp the positions describe.
    sequence: u64,
    /// The moved region of each recent advance (`None`: nothing moved), oldest first.
    history: std::collections::VecDeque<(u64, Option<Region>)>,
}

impl IncrementalWarp {
    /// The warp of `deformed` (sequence 0); nothing is written until [`Self::write_into`].
    pub fn new(
        source: Arc<Volume>,
        rest: Arc<TetMesh>,
        deformed: &[Vector3<f64>],
        grid: Grid,
        options: WarpOptions,
    ) -> Result<Self, WarpError> {
        check_size(&grid, 4, &options)?;
        Sampler::new(&source, &options)?;
        let maps = tet_maps(&rest, deformed, &source.grid(), &grid)?;
        Ok(Self {
            source,
            rest,
            grid,
            options,
            positions: deformed.to_vec(),
            maps,
            sequence: 0,
            history: Default::default(),
        })
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The warp the last positions describe.
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    /// Tets skipped as inverted, degenerate or off the grid at the current positions.
    pub fn skipped_tets(&self) -> u64 {
        self.maps.iter().filter(|m| m.is_none()).count() as u64
    }

    /// Takes new deformed positions: the box covering the old and new extents of every tet
    /// with a node that moved more than `tolerance` is what changed. Returns the new sequence.
    pub fn advance(&mut self, deformed: &[Vector3<f64>], tolerance: f64) -> Result<u64, WarpError> {
        if deformed.len() != self.positions.len() {
            return Err(WarpError::NodeCount { got: deformed.len(), expected: self.positions.len() });
        }
        let moved: Vec<bool> = self.positions.iter().zip(deformed).map(|(a, b)| (a - b).norm() > tolerance).collect();
        // A node that moved less keeps the place the warp last gave it, so that the tets
        // around it keep their maps: what an earlier volume holds of them stays this warp's,
        // and slow drift is caught once it adds up to the tolerance.
        let applied: Vec<Vector3<f64>> = self
            .positions
            .iter()
            .zip(deformed)
            .zip(&moved)
            .map(|((old, new), m)| if *m { *new } else { *old })
            .collect();
        let maps = tet_maps(&self.rest, &applied, &self.source.grid(), &self.grid)?;
        let mut region: Option<Region> = None;
        let mut grow = |lo_in: [usize; 3], hi_in: [usize; 3]| {
            let (lo, hi) = region.get_or_insert((lo_in, hi_in));
            for a in 0..3 {
                lo[a] = lo[a].min(lo_in[a]);
                hi[a] = hi[a].max(hi_in[a]);
            }
        };
        for (t, tet) in self.rest.tets().iter().enumerate() {
            if !tet.iter().any(|n| moved[*n as usize]) {
                continue;
            }
            for m in [&self.maps[t], &maps[t]].into_iter().flatten() {
                grow(m.lo, m.hi);
            }
            // Inverted tets have no map: cover their nodes' positions too.
            if self.maps[t].is_none() || maps[t].is_none() {
                for p in tet.iter().flat_map(|n| [self.positions[*n as usize], applied[*n as usize]]) {
                    let ijk = self.grid.index_from_world(p);
                    let c = [0, 1, 2].map(|a| ijk[a].clamp(0.0, (self.grid.dims[a] - 1) as f64));
                    grow(c.map(|v| v.floor() as usize), c.map(|v| v.ceil() as usize));
                }
            }
        }
        self.positions = applied;
        self.maps = maps;
        self.sequence += 1;
        self.history.push_back((self.sequence, region));
        if self.history.len() > HISTORY {
            self.history.pop_front();
        }
        Ok(self.sequence)
    }

    /// Brings `out` to the current warp. `holds`: the sequence of the warp `out` holds, if
    /// it holds one of this warp's (its owner's knowledge); then only the regions moved
    /// since are re-warped, else all of it. Returns the work done (`voxels`: those
    /// re-warped; zero when `out` was up to date).
    pub fn write_into(&self, out: &mut [f32], holds: Option<u64>) -> Result<WarpStats, WarpError> {
        if out.len() != self.grid.len() {
            return Err(WarpError::BufferSize { got: out.len(), expected: self.grid.len() });
        }
        let whole: Region = ([0; 3], self.grid.dims.map(|d| d - 1));
        let oldest_known = self.history.front().map_or(self.sequence, |(s, _)| s - 1);
        let region = match holds {
            Some(s) if s == self.sequence => return Ok(WarpStats::default()),
            Some(s) if s < self.sequence && s >= oldest_known => {
                let mut union: Option<Region> = None;
                for (_, moved) in self.history.iter().filter(|(q, _)| *q > s) {
                    if let Some((lo, hi)) = moved {
                        let (ulo, uhi) = union.get_or_insert((*lo, *hi));
                        for a in 0..3 {
                            ulo[a] = ulo[a].min(lo[a]);
                            uhi[a] = uhi[a].max(hi[a]);
                        }
                    }
                }
                match union {
                    Some(region) => region,
                    None => return Ok(WarpStats::default()),
                }
            }
            _ => whole,
        };
        let mut stats = self.rewarp(out, region)?;
        if region == whole {
            stats.skipped_tets = self.skipped_tets();
        }
        Ok(stats)
    }

    /// Re-warps the box `[lo, hi]` of `out`: its initial values, then every tet over it.
    fn rewarp(&self, out: &mut [f32], (lo, hi): Region) -> Result<WarpStats, WarpError> {
        let sampler = Sampler::new(&self.source, &self.options)?;
        let identity = self.grid.index_map_to(&self.source.grid());
        let [nx, ny, _] = self.grid.dims;
        let depth = slab_depth::<f32>(nx, ny, self.options.path, REGION_SLAB_BYTES);
        let bins = slab_bins(&self.maps, lo[2], hi[2], depth);
        let (maps, options) = (&self.maps, &self.options);
        let background = options.background;
        let mut stats = out[lo[2] * nx * ny..(hi[2] + 1) * nx * ny]
            .par_chunks_mut(nx * ny * depth)
            .enumerate()
            .map(|(s, slab)| {
                let k0 = lo[2] + s * depth;
                for (dk, slice) in slab.chunks_mut(nx * ny).enumerate() {
                    for j in lo[1]..=hi[1] {
                        let row = &mut slice[nx * j + lo[0]..=nx * j + hi[0]];
                        if options.keep_uncovered {
                            for (di, v) in row.iter_mut().enumerate() {
                                *v = initial_value(&sampler, &identity, true, lo[0] + di, j, k0 + dk);
                            }
                        } else {
                            fill(row, background);
                        }
                    }
                }
                let (lo, hi) = ([lo[0], lo[1]], [hi[0], hi[1]]);
                rasterize_slab(slab, [nx, ny], k0, &bins[s], maps, &sampler, options.scheme, lo, hi)
            })
            .reduce(WarpStats::default, |mut a, b| {
                a += b;
                a
            });
        stats.voxels = ((hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1)) as u64;
        Ok(stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use defvol_core::mesh::generate::{self, CellSplit};
    use defvol_core::volume::phantom;

    /// Nodes thrown far off (a runaway deformation) give a default grid too large to warp,
    /// refused by name with what it would need, where its voxel count would wrap 64 bits.
    #[test]
    fn a_runaway_deformations_grid_is_refused_by_name() {
        let source = phantom::phantom([24, 20, 16], 2.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 40, CellSplit::Five).unwrap();
        let limit_mib = WarpOptions::default().max_bytes >> 20;
        for far in [1e4, 1e30] {
            let mut thrown = mesh.nodes().to_vec();
            thrown[0] = Vector3::repeat(far);
            let grid = default_grid(&source, &thrown);
            assert!(grid.dims.iter().all(|&d| d as f64 >= far.min(usize::MAX as f64) / 2.0 - 2.0), "{:?}", grid.dims);
            let err = warp(&source, &mesh, &thrown, &grid, &WarpOptions::default()).unwrap_err();
            let WarpError::TooLarge { dims, needed_mib, limit_mib: limit } = err else { panic!("{err}") };
            assert_eq!((dims, limit), (grid.dims, limit_mib));
            let bytes = grid.dims.iter().map(|&d| d as f64).product::<f64>() * 4.0;
            let want = (bytes.min(u64::MAX as f64) / (1u64 << 20) as f64).ceil() as u64;
            assert!(needed_mib.abs_diff(want) <= want / 1_000_000, "{needed_mib} MiB against {want}");
            assert!(err.to_string().contains(&format!("{needed_mib} MiB")), "{err}");
        }
    }

    /// A press on a turned mesh re-warps only its region, the tets' spans streamed and
    /// clipped to the region's box, and leaves the scalar path's full warp, bit for bit.
    #[test]
    fn a_press_on_a_turned_mesh_re_warps_to_the_scalar_paths_bits() {
        let source = Arc::new(phantom::phantom([96, 72, 56], 2.0).unwrap());
        let (lo, hi) = source.bounds();
        let mesh = Arc::new(generate::lattice_for_box(lo, hi, 300, CellSplit::Five).unwrap());
        let centre = (lo + hi) / 2.0;
        let turn = nalgebra::Rotation3::from_euler_angles(0.6, 0.4, 0.3);
        let turned: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| centre + turn * (p - centre)).collect();
        let grid = default_grid(&source, &turned);
        let options = WarpOptions { background: -7.0, ..Default::default() };
        let mut warp =
            IncrementalWarp::new(source.clone(), mesh.clone(), &turned, grid.clone(), options.clone()).unwrap();
        let mut out = vec![f32::NAN; grid.len()];
        warp.write_into(&mut out, None).unwrap();
        let tip = turned[turned.len() / 3];
        let pressed: Vec<Vector3<f64>> = turned
            .iter()
            .map(|p| match (p - tip).norm() {
                d if d < 30.0 => p - Vector3::z() * (4.0 * (1.0 - d / 30.0)),
                _ => *p,
            })
            .collect();
        let sequence = warp.advance(&pressed, 1e-9).unwrap();
        let stats = warp.write_into(&mut out, Some(sequence - 1)).unwrap();
        assert!(stats.voxels > 0 && stats.voxels < grid.len() as u64 / 4, "a local region: {stats:?}");
        let scalar = WarpOptions { path: WarpPath::Scalar, ..options };
        let (expected, _) = warp_samples::<f32>(&source, &mesh, &pressed, &grid, &scalar).unwrap();
        let differ = out.iter().zip(&expected).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        assert_eq!(differ, 0, "{differ} voxels differ");
        // A buffer said to hold the warp before has only the region written: no span
        // reaches past its box.
        let mut blank = vec![f32::NAN; grid.len()];
        assert_eq!(warp.write_into(&mut blank, Some(sequence - 1)).unwrap(), stats);
        let written: Vec<usize> = (0..blank.len()).filter(|&v| !blank[v].is_nan()).collect();
        assert_eq!(written.len() as u64, stats.voxels);
        assert!(written.iter().all(|&v| blank[v].to_bits() == expected[v].to_bits()));
    }

    /// The fast path (eight-lane samples, slabs of slices) gives the scalar path's bits on a
    /// rotated mesh whose tets share faces on many voxels, and on the mesh at rest (runs
    /// along the source's rows), with and without the source kept where no tet covers.
    #[test]
    fn the_fast_path_gives_the_scalar_paths_bits() {
        let source = phantom::phantom([96, 72, 96], 2.0).unwrap();
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, 300, CellSplit::Five).unwrap();
        let centre = (lo + hi) / 2.0;
        let turn = nalgebra::Rotation3::from_euler_angles(0.6, 0.4, 0.3);
        let turned: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| centre + turn * (p - centre)).collect();
        for (positions, keep_uncovered) in [(turned.clone(), false), (turned, true), (mesh.nodes().to_vec(), false)] {
            let grid = default_grid(&source, &positions);
            let depth = slab_depth::<f32>(grid.dims[0], grid.dims[1], WarpPath::Fast, SLAB_BYTES);
            assert!(grid.dims[2] > 2 * depth, "tets must cross slabs: {:?}", grid.dims);
            let run = |path| {
                let options = WarpOptions { keep_uncovered, path, background: -7.0, ..Default::default() };
                warp_samples::<f32>(&source, &mesh, &positions, &grid, &options).unwrap()
            };
            let ((fast, fast_stats), (scalar, scalar_stats)) = (run(WarpPath::Fast), run(WarpPath::Scalar));
            assert_eq!(fast_stats, scalar_stats);
            assert!(fast_stats.inside > 10_000, "{fast_stats:?}");
            let differ = fast.iter().zip(&scalar).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
            assert_eq!(differ, 0, "{differ} voxels differ (keep_uncovered {keep_uncovered})");
        }
    }

    /// The background fill writes exactly its slice, every sample the value's bits, at any
    /// length and alignment, in f32 (`rep stosd`) and f64.
    #[test]
    fn the_fill_writes_exactly_its_samples() {
        for len in 0..70 {
            for offset in 0..4 {
                let mut samples = vec![f32::NAN; len + 8];
                fill(&mut samples[offset..offset + len], -7.25);
                let changed: Vec<usize> = (0..samples.len()).filter(|&i| !samples[i].is_nan()).collect();
                assert_eq!(changed, (offset..offset + len).collect::<Vec<_>>(), "f32, {len} at {offset}");
                assert!(changed.iter().all(|&i| samples[i].to_bits() == (-7.25f32).to_bits()));
                let mut wide = vec![f64::NAN; len + 8];
                fill(&mut wide[offset..offset + len], -7.25);
                assert!(wide.iter().enumerate().all(|(i, v)| (offset..offset + len).contains(&i) == (*v == -7.25)));
            }
        }
    }

    /// Three buffers taking turns, as shared-memory samples do: each is brought from the
    /// warp it last held to the current one, and always equals a full warp.
    #[test]
    fn buffers_taking_turns_always_hold_the_current_warp() {
        let source = Arc::new(phantom::phantom([48, 32, 24], 5.0).unwrap());
        let (lo, hi) = source.bounds();
        let mesh = Arc::new(generate::lattice_for_box(lo, hi, 600, CellSplit::Five).unwrap());
        let options = WarpOptions { keep_uncovered: true, ..Default::default() };
        let grid = source.grid();
        let mut warp =
            IncrementalWarp::new(source.clone(), mesh.clone(), mesh.nodes(), grid.clone(), options.clone()).unwrap();
        let mut buffers: Vec<(Vec<f32>, Option<u64>)> = (0..3).map(|_| (vec![f32::NAN; grid.len()], None)).collect();
        let centre = (lo + hi) / 2.0;
        for step in 1..=9 {
            // A probe pressing in at a point that wanders: a local change each step.
            let tip = centre
                + Vector3::new(40.0 * (step as f64 * 0.7).sin(), 20.0 * (step as f64 * 0.4).cos(), hi.z - centre.z);
            let pressed: Vec<Vector3<f64>> = mesh
                .nodes()
                .iter()
                .map(|p| {
                    let d = (p - tip).norm();
                    if d < 40.0 {
                        p - Vector3::z() * (3.0 * step as f64 / 9.0 * (1.0 - d / 40.0))
                    } else {
                        *p
                    }
                })
                .collect();
            let sequence = warp.advance(&pressed, 1e-9).unwrap();
            let (buffer, holds) = &mut buffers[step % 3];
            let stats = warp.write_into(buffer, *holds).unwrap();
            *holds = Some(sequence);
            let (full, _) = super::warp(&source, &mesh, &pressed, &grid, &options).unwrap();
            assert!(
                buffer.iter().zip(full.data()).all(|(a, b)| a.to_bits() == b.to_bits()),
                "step {step}: the buffer differs from a full warp"
            );
            if step > 3 {
                assert!(
                    stats.voxels < grid.len() as u64,
                    "step {step}: a buffer three warps behind is re-warped in part, not whole ({stats:?})"
                );
            } else {
                assert_eq!(stats.voxels, grid.len() as u64, "step {step}: a fresh buffer is warped whole");
            }
        }
        // Up to date: nothing to do.
        let (buffer, holds) = &mut buffers[0];
        assert_eq!(warp.write_into(buffer, *holds).unwrap().voxels, 0);
    }
}
