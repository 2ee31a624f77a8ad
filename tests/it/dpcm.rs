//! DPCM accuracy: exact rest, wave speed against the discrete wave equation, plasticity,
//! energy, the fast path against the general form, and an independent f64 reference.

use defvol::dpcm::kernels::{self, TILE};
use defvol::dpcm::Script;
use defvol::dpcm::{DpcmConfig, DpcmError, Interaction, Links, Marker, MarkerParams, Surface, Topology};

/// 1 mm phyxels, 1 ms steps, 0.1 g: h²/m = 0.01, h/m = 10.
fn config(
    width: usize,
    height: usize,
    topology: Topology,
    link: Option<Interaction>,
    ground: Interaction,
) -> DpcmConfig {
    DpcmConfig {
        description: String::new(),
        width,
        height,
        spacing: 1e-3,
        dt: 1e-3,
        mass: 1e-4,
        rest_height: 0.0,
        ground,
        links: Links { topology, probability: 1.0, seed: 0, axial: link, diagonal: None },
        marker: MarkerParams { stiffness: 50.0, damping: 1e-3, threshold: 0.004, flattening: 0.0 },
        textures: Vec::new(),
        render: Default::default(),
        script: Script::default(),
    }
}

fn gaussian(width: usize, height: usize, sigma: f64, amplitude: f64) -> Vec<f32> {
    let (cx, cy) = ((width / 2) as f64, (height / 2) as f64);
    (0..width * height)
        .map(|i| {
            let (x, y) = ((i % width) as f64 - cx, (i / width) as f64 - cy);
            (amplitude * (-(x * x + y * y) / (2.0 * sigma * sigma)).exp()) as f32
        })
        .collect()
}

#[test]
fn a_grid_at_a_non_zero_rest_height_stays_bit_exact_for_a_million_steps() {
    // The seed saw noise at rest from quantised heights; in f32 with link forces as sums of
    // differences, rest is exact. Both the fast path (regular) and the general one
    // (stochastic), with damping and a plastic ground link.
    for probability in [1.0, 0.6] {
        let mut c = config(
            16,
            16,
            Topology::Eight,
            Some(Interaction::DampedSpring { stiffness: 15.0, damping: 2e-4 }),
            Interaction::Plastic { stiffness: 10.0, damping: 0.05, threshold: 2e-4 },
        );
        c.rest_height = 0.003_7;
        c.links.probability = probability;
        let mut surface = Surface::new(&c).unwrap();
        let rest = surface.heights();
        for _ in 0..1_000_000 {
            surface.step(&[]);
        }
        assert_eq!(surface.heights(), rest, "probability {probability}");
        assert_eq!(surface.previous_heights(), rest);
        assert!(rest.iter().all(|&z| z == 0.003_7_f32));
        assert!(surface.deviations().iter().chain(surface.rest_deviations()).all(|&u| u == 0.0));
    }
}

/// Radius of the outgoing ring's crest along +x from the centre row (parabolic sub-phyxel).
fn crest_radius(surface: &Surface, from: usize) -> f64 {
    let (w, h) = (surface.width(), surface.height());
    let heights = surface.heights();
    let row = &heights[(h / 2) * w..(h / 2 + 1) * w];
    let cx = w / 2;
    let peak = (cx + from..w - 1).max_by(|&a, &b| row[a].total_cmp(&row[b])).unwrap();
    let (l, m, r) = (f64::from(row[peak - 1]), f64::from(row[peak]), f64::from(row[peak + 1]));
    (peak - cx) as f64 + 0.5 * (l - r) / (l - 2.0 * m + r)
}

fn ring_speed(topology: Topology, diagonal: Option<Interaction>) -> f64 {
    let spring = Interaction::Elastic { stiffness: 25.0 };
    let mut c = config(241, 241, topology, Some(spring), Interaction::Elastic { stiffness: 0.0 });
    c.links.diagonal = diagonal;
    let mut surface = Surface::new(&c).unwrap();
    surface.set_heights(&gaussian(241, 241, 4.0, 1e-4)).unwrap();
    let (t1, t2) = (60, 120);
    for _ in 0..t1 {
        surface.step(&[]);
    }
    let r1 = crest_radius(&surface, 12);
    for _ in t1..t2 {
        surface.step(&[]);
    }
    let r2 = crest_radius(&surface, 12);
    (r2 - r1) / (t2 - t1) as f64
}

#[test]
fn a_disturbance_spreads_at_the_discrete_wave_speed_and_faster_with_diagonals() {
    // m z'' = Σ k (z_j - z_i): long waves travel at c² = (k_axial + 2 k_diagonal)·a²/m
    // (a diagonal link reaches √2·a, in both axes). Per step: c = √(Σ k h²/m) phyxels.
    // A σ = 4 phyxel pulse is long enough that the lattice's dispersion (group velocity
    // cos(κa/2) ≈ 0.99 of c) stays inside the 3 % bound.
    let a = 25.0 * 0.01; // k h²/m
    let four = ring_speed(Topology::Four, None);
    let diagonal = ring_speed(Topology::Diagonal, None);
    let eight = ring_speed(Topology::Eight, None);
    let expect = |v: f64, c: f64, what: &str| {
        assert!((v / c - 1.0).abs() < 0.03, "{what}: measured {v:.4} phyxels/step, predicted {c:.4}")
    };
    expect(four, f64::sqrt(a), "four neighbours");
    expect(diagonal, f64::sqrt(2.0 * a), "diagonals only");
    expect(eight, f64::sqrt(3.0 * a), "eight neighbours");
    // The seed's figure 12: the same pattern, faster on the diagonals.
    assert!(diagonal > 1.3 * four);
}

#[test]
fn a_plastic_ground_keeps_the_track_and_an_elastic_one_returns_to_rest() {
    let run = |ground: Interaction| {
        let mut c = config(64, 48, Topology::None, None, ground);
        c.marker = MarkerParams { stiffness: 100.0, damping: 5e-3, threshold: 0.005, flattening: 0.3 };
        c.script = Script {
            markers: 1,
            pattern: defvol::dpcm::Pattern::Lines,
            speed: 0.05,
            depth: 0.002,
            leave_after: Some(0.6),
        };
        let mut surface = Surface::new(&c).unwrap();
        let watched = 24 * 64 + 32; // on the marker's row, half way along
        let mut deepest = 0.0f32;
        for step in 0..4000 {
            let markers = c.script.markers_at(&c, step as f64 * c.dt);
            surface.step(&markers);
            deepest = deepest.min(surface.heights()[watched]);
        }
        (surface.displacement(), deepest, watched)
    };
    let (elastic, elastic_deepest, watched) = run(Interaction::DampedSpring { stiffness: 10.0, damping: 0.05 });
    let (plastic, deepest, _) = run(Interaction::Plastic { stiffness: 10.0, damping: 0.05, threshold: 2e-4 });
    assert!(elastic_deepest < -1e-3 && deepest < -1e-3, "the marker pressed in: {elastic_deepest} {deepest}");
    let elastic_left = elastic.iter().fold(0.0f32, |m, d| m.max(d.abs()));
    assert!(elastic_left < 1e-6, "elastic ground still displaced by {elastic_left} m");
    // Plastic: the rest point was dragged to the deepest point + threshold; the phyxel
    // springs back by the elastic band only.
    let expected = f64::from(deepest) + 2e-4;
    assert!(
        (f64::from(plastic[watched]) - expected).abs() < 0.03 * expected.abs(),
        "track {} m, expected {expected} m",
        plastic[watched]
    );
    // The track is permanent: far from the path nothing moved.
    assert_eq!(plastic[2 * 64 + 32], 0.0);
}

/// The leapfrog's conserved quantity: ½m|v(n-½)|² + ½ zᵀ(n) K z(n-1), with the link and
/// ground springs of an eight-neighbour grid. Viscous forces can only remove it.
fn shadow_energy(surface: &Surface, k_axial: f64, k_diagonal: f64, k_ground: f64) -> f64 {
    let c = surface.config();
    let (w, h) = (surface.width(), surface.height());
    let (z, zp) = (&surface.heights()[..], &surface.previous_heights()[..]);
    let at = |v: &[f32], x: usize, y: usize| f64::from(v[y * w + x]);
    let mut e = 0.0;
    for y in 0..h {
        for x in 0..w {
            let v = (at(z, x, y) - at(zp, x, y)) / c.dt;
            e += 0.5 * c.mass * v * v + 0.5 * k_ground * (at(z, x, y) - c.rest_height) * (at(zp, x, y) - c.rest_height);
            for (dx, dy, k) in [(1, 0, k_axial), (0, 1, k_axial), (1, 1, k_diagonal), (-1, 1, k_diagonal)] {
                let (nx, ny) = (x as isize + dx, y as isize + dy);
                if nx < 0 || nx >= w as isize || ny >= h as isize {
                    continue;
                }
                let (nx, ny) = (nx as usize, ny as usize);
                e += 0.5 * k * (at(z, nx, ny) - at(z, x, y)) * (at(zp, nx, ny) - at(zp, x, y));
            }
        }
    }
    e
}

#[test]
fn without_markers_and_with_damping_energy_never_grows() {
    let mut c = config(
        64,
        64,
        Topology::Eight,
        Some(Interaction::DampedSpring { stiffness: 25.0, damping: 2e-4 }),
        Interaction::DampedSpring { stiffness: 0.5, damping: 5e-4 },
    );
    c.links.diagonal = Some(Interaction::DampedSpring { stiffness: 12.5, damping: 1e-4 });
    let mut surface = Surface::new(&c).unwrap();
    surface.set_heights(&gaussian(64, 64, 3.0, 1e-3)).unwrap();
    surface.step(&[]);
    let e0 = shadow_energy(&surface, 25.0, 12.5, 0.5);
    let mut last = e0;
    for step in 0..3000 {
        surface.step(&[]);
        let e = shadow_energy(&surface, 25.0, 12.5, 0.5);
        assert!(e <= last + 1e-6 * e0, "energy grew at step {step}: {last} -> {e}");
        last = e;
    }
    assert!(last < 0.5 * e0, "damping removed too little: {e0} -> {last}");
}

fn busy_config(probability: f64) -> DpcmConfig {
    let mut c = config(
        70,
        53,
        Topology::Eight,
        Some(Interaction::DampedSpring { stiffness: 20.0, damping: 3e-4 }),
        Interaction::Plastic { stiffness: 10.0, damping: 0.02, threshold: 3e-4 },
    );
    c.links.diagonal = Some(Interaction::DampedSpring { stiffness: 8.0, damping: 1e-4 });
    c.links.probability = probability;
    c.links.seed = 3;
    c.script =
        Script { markers: 4, pattern: defvol::dpcm::Pattern::Wander, speed: 0.08, depth: 0.0015, leave_after: None };
    c
}

#[test]
fn the_fast_interior_rows_equal_the_general_form_bit_for_bit() {
    for probability in [1.0, 0.5] {
        fast_rows_match_the_general_form(probability);
    }
}

fn fast_rows_match_the_general_form(probability: f64) {
    let c = busy_config(probability);
    let mut surface = Surface::new(&c).unwrap();
    for step in 0..300 {
        let markers = c.script.markers_at(&c, step as f64 * c.dt);
        // The general form for every phyxel, markers gathered over the whole list.
        let mut probe = surface.clone();
        probe.bin_markers(&markers);
        let bins = probe.bins().clone();
        let (w, h) = (surface.width(), surface.height());
        let (z, zp) = (surface.deviations().to_vec(), surface.previous_deviations().to_vec());
        let mut rest = surface.rest_deviations().to_vec();
        let coeffs = *surface.coeffs();
        let expected: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                rest[i] = kernels::plastic_rest(&coeffs, rest[i], z[i]);
                let (ga, gb) = surface.ground_coeffs(i);
                let base = kernels::phyxel_update(&coeffs, ga, gb, rest[i], &z, &zp, w, h, x, y);
                let tile = bins.tile(x / TILE, y / TILE);
                let mut push = 0.0f32;
                for &m in tile {
                    push += kernels::marker_term(&bins.markers[m as usize], x as f32, y as f32, z[i], z[i] - zp[i]);
                }
                base + push
            })
            .collect();
        surface.step(&markers);
        assert_eq!(surface.deviations(), &expected[..], "p = {probability}, step {step}");
        assert_eq!(surface.rest_deviations(), &rest[..], "p = {probability}, step {step}");
    }
}

/// An independent f64 DPCM: plain loops over phyxels, links and markers.
struct Reference {
    w: usize,
    h: usize,
    z: Vec<f64>,
    zp: Vec<f64>,
    rest: Vec<f64>,
}

impl Reference {
    fn step(&mut self, c: &DpcmConfig, coeffs: &kernels::Coeffs, markers: &[(Marker, f64)]) {
        let (h, m, s) = (c.dt, c.mass, c.spacing);
        let Interaction::Plastic { stiffness: kg, damping: cg, threshold } = c.ground else { panic!() };
        let (
            Some(Interaction::DampedSpring { stiffness: ka, damping: ca }),
            Some(Interaction::DampedSpring { stiffness: kd, damping: cd }),
        ) = (c.links.axial, c.links.diagonal)
        else {
            panic!()
        };
        let mut next = vec![0.0; self.z.len()];
        for y in 0..self.h {
            for x in 0..self.w {
                let i = y * self.w + x;
                let (z, v) = (self.z[i], (self.z[i] - self.zp[i]) / h);
                self.rest[i] = self.rest[i].clamp(z - threshold, z + threshold);
                let mut f = -kg * (z - self.rest[i]) - cg * v;
                for (dx, dy) in [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (-1, 1), (1, 1)] {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    if nx < 0 || ny < 0 || nx >= self.w as isize || ny >= self.h as isize {
                        continue;
                    }
                    let j = ny as usize * self.w + nx as usize;
                    // The same random draw of the topology (an input, not the physics).
                    let (owner, dir) = match (dx, dy) {
                        (1, 0) => (i, 0),
                        (-1, 0) => (j, 0),
                        (0, 1) => (i, 1),
                        (0, -1) => (j, 1),
                        (1, 1) => (i, 2),
                        (-1, -1) => (j, 2),
                        (-1, 1) => (i, 3),
                        _ => (j, 3),
                    };
                    if !kernels::link_kept(coeffs, owner as u32, dir) {
                        continue;
                    }
                    let (k, cv) = if dx == 0 || dy == 0 { (ka, ca) } else { (kd, cd) };
                    f += k * (self.z[j] - z) + cv * ((self.z[j] - self.zp[j]) / h - v);
                }
                for (marker, step_dz) in markers {
                    let p = marker.params.unwrap_or(c.marker);
                    let (dx, dy) = ((x as f64 - marker.col) * s, (y as f64 - marker.row) * s);
                    let dz = (z - marker.height) / (1.0 - p.flattening);
                    let d = (dx * dx + dy * dy + dz * dz).sqrt();
                    if d < p.threshold {
                        let dir = if d > 0.0 { dz / d } else { -1.0 };
                        f += p.stiffness * (p.threshold - d) * dir + p.damping * (step_dz / h - v);
                    }
                }
                next[i] = 2.0 * z - self.zp[i] + f * h * h / m;
            }
        }
        self.zp = std::mem::replace(&mut self.z, next);
    }
}

#[test]
fn f32_surfaces_follow_an_independent_f64_reference() {
    for probability in [1.0, 0.5] {
        let c = busy_config(probability);
        let mut surface = Surface::new(&c).unwrap();
        let n = c.width * c.height;
        let mut reference =
            Reference { w: c.width, h: c.height, z: vec![0.0; n], zp: vec![0.0; n], rest: vec![0.0; n] };
        let mut last = std::collections::HashMap::new();
        for step in 0..600 {
            let markers = c.script.markers_at(&c, step as f64 * c.dt);
            let with_dz: Vec<(Marker, f64)> =
                markers.iter().map(|m| (*m, last.get(&m.id).map_or(0.0, |l| m.height - l))).collect();
            last = markers.iter().map(|m| (m.id, m.height)).collect();
            reference.step(&c, surface.coeffs(), &with_dz);
            surface.step(&markers);
        }
        let peak = reference.z.iter().fold(0.0f64, |m, z| m.max(z.abs()));
        let worst =
            surface.heights().iter().zip(&reference.z).map(|(a, b)| (f64::from(*a) - b).abs()).fold(0.0, f64::max);
        assert!(peak > 5e-4, "the markers engraved too little: {peak}");
        assert!(worst < 2e-3 * peak, "p = {probability}: f32 off the f64 reference by {worst:e} of a peak {peak:e}");
    }
}

#[test]
fn markers_are_binned_into_exactly_the_tiles_they_reach() {
    let c = busy_config(1.0);
    let mut surface = Surface::new(&c).unwrap();
    let mut markers: Vec<Marker> = (0..40)
        .map(|i| Marker {
            id: i,
            col: (i * 37 % 90) as f64 - 10.0,
            row: (i * 11 % 70) as f64 - 8.0,
            height: 0.0,
            params: None,
        })
        .collect();
    markers.push(Marker { id: 99, col: f64::NAN, row: 3.0, height: 0.0, params: None });
    let stats = surface.bin_markers(&markers);
    assert_eq!(stats.markers_dropped, 1);
    let bins = surface.bins();
    let reach = c.marker.threshold / c.spacing;
    let mut off_grid = 0;
    for (index, m) in bins.markers.iter().enumerate() {
        let mut anywhere = false;
        for ty in 0..bins.tiles_y {
            for tx in 0..bins.tiles_x {
                // Brute force: does any phyxel of the tile lie within reach?
                let touches = (ty * TILE..((ty + 1) * TILE).min(c.height)).any(|y| {
                    (tx * TILE..((tx + 1) * TILE).min(c.width)).any(|x| {
                        (x as f64 - f64::from(m.col)).abs() <= reach + 1.0
                            && (y as f64 - f64::from(m.row)).abs() <= reach + 1.0
                    })
                });
                let listed = bins.tile(tx, ty).contains(&(index as u32));
                anywhere |= listed;
                if !touches {
                    assert!(!listed, "marker {index} listed in tile ({tx}, {ty}) it cannot reach");
                }
                // Every phyxel the marker can push is in a tile that lists it.
                for y in ty * TILE..((ty + 1) * TILE).min(c.height) {
                    for x in tx * TILE..((tx + 1) * TILE).min(c.width) {
                        let pushed = kernels::marker_term(m, x as f32, y as f32, 0.0, 0.0) != 0.0;
                        assert!(
                            !pushed || listed,
                            "marker {index} pushes ({x}, {y}) but tile ({tx}, {ty}) does not list it"
                        );
                    }
                }
            }
        }
        off_grid += usize::from(!anywhere);
    }
    assert_eq!(stats.markers_off_grid, off_grid);
    assert_eq!(stats.markers_applied + stats.markers_off_grid + stats.markers_dropped, markers.len());
    // The run goes on after the bad marker.
    surface.step(&markers);
    assert!(surface.heights().iter().all(|z| z.is_finite()));
}

#[test]
fn impossible_parameters_are_refused_with_their_name() {
    let base = config(
        32,
        32,
        Topology::Four,
        Some(Interaction::Elastic { stiffness: 25.0 }),
        Interaction::Elastic { stiffness: 1.0 },
    );
    let mut c = base.clone();
    c.dt = 0.01;
    let Err(DpcmError::Unstable { dt_max, .. }) = Surface::new(&c) else { panic!("dt 0.01 accepted") };
    assert!(dt_max > 1e-3 && dt_max < 1e-2, "dt_max {dt_max}");
    c.dt = dt_max * 0.99;
    Surface::new(&c).unwrap();
    let mut c = base.clone();
    c.links.axial = Some(Interaction::Plastic { stiffness: 1.0, damping: 0.0, threshold: 1e-3 });
    let err = Surface::new(&c).unwrap_err().to_string();
    assert!(err.contains("links.axial") && err.contains("plastic"), "{err}");
    let mut c = base.clone();
    c.mass = -1.0;
    assert!(Surface::new(&c).unwrap_err().to_string().contains("`mass`"));
    let mut c = base;
    c.marker.flattening = 1.0;
    assert!(Surface::new(&c).unwrap_err().to_string().contains("marker.flattening"));
    assert!(matches!(DpcmConfig::preset("mud"), Err(DpcmError::UnknownPreset(_))));
    let err = DpcmConfig::from_yaml(
        "width: 10\nheight: 10\nspacing: 0.001\ndt: 0.001\nmass: 1\nground: { kind: bouncy }\n",
        "test.yaml",
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("test.yaml: ground.kind: unknown variant, expected one of `elastic`"), "{err}");
    assert!(err.ends_with("at line 6 column 17") && !err.contains("bouncy"), "the text found is withheld: {err}");
}

#[test]
fn every_preset_loads_and_runs_stably() {
    for (name, _) in defvol::dpcm::PRESETS {
        let mut c = DpcmConfig::preset(name).unwrap();
        assert!(!c.description.is_empty(), "{name} has no description");
        (c.width, c.height) = (96, 96);
        let mut surface = Surface::new(&c).unwrap();
        let mut peak = 0.0f32;
        for step in 0..1500 {
            let markers = c.script.markers_at(&c, step as f64 * c.dt);
            surface.step(&markers);
            peak = surface.displacement().iter().fold(peak, |m, d| m.max(d.abs()));
        }
        let depth = c.script.depth as f32;
        assert!(
            peak > 0.2 * depth && peak < 5.0 * depth,
            "{name}: peak displacement {peak} for a {depth} m deep marker"
        );
        assert!(surface.heights().iter().all(|z| z.is_finite()), "{name}");
    }
}

#[test]
fn waves_dying_out_leave_no_subnormal_heights() {
    // Regression: far-field waves decayed into f32 subnormals, and every step over them ran
    // ~2x slower on x86. They are flushed to 0 below kernels::FLUSH_BELOW.
    let mut c = DpcmConfig::preset("water").unwrap();
    (c.width, c.height) = (48, 48);
    c.ground = Interaction::DampedSpring { stiffness: 5.0, damping: 0.02 };
    let mut surface = Surface::new(&c).unwrap();
    surface.set_heights(&gaussian(48, 48, 2.0, 1e-3)).unwrap();
    let mut saw_flush_range = false;
    for _ in 0..20_000 {
        surface.step(&[]);
        let u = surface.deviations();
        assert!(u.iter().all(|v| *v == 0.0 || v.is_normal()), "a subnormal height");
        saw_flush_range |= u.iter().any(|v| *v != 0.0 && v.abs() < 1e-15);
    }
    assert!(saw_flush_range, "the run never got near the flush threshold");
    assert!(surface.deviations().iter().all(|v| *v == 0.0), "damped waves did not die out to exact rest");
}
