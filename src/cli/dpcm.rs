//! `defvol dpcm`: run a DPCM preset under scripted, recorded or streamed markers and write
//! its renderings.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::Isometry3;

use defvol::backend::BackendChoice;
use defvol::dpcm::engine::DpcmEngine;
use defvol::dpcm::markers::{Calibration, MotionFile, UdpSource};
use defvol::dpcm::render;
use defvol::dpcm::{DpcmConfig, Marker, StepStats};
use defvol::scene::BackendArgs;

use super::choices::CliColorMap;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Output {
    /// colour.png: the colour map of the displacement.
    Colour,
    /// bump.png: lit normals from the height derivatives.
    Bump,
    /// surface.vtu: the height field as triangles (the displacement mesh).
    Mesh,
    /// height.mha: Z as a 32-bit float image, metres.
    Height,
}

#[derive(clap::Args)]
pub struct DpcmArgs {
    /// A preset from config/dpcm: water, loose_soil, sand, oil_painting, fossil.
    #[arg(long, default_value = "water")]
    preset: String,
    /// A DPCM configuration file (YAML, as the presets), instead of the preset.
    #[arg(long, conflicts_with = "preset")]
    config: Option<PathBuf>,
    /// Grid size, WxH phyxels (overrides the configuration's).
    #[arg(long)]
    size: Option<String>,
    /// Motion file: CSV `time,marker,x,y,z` (seconds, id, the marker's tip in world metres:
    /// a tip at the surface's rest height touches it, one 1 mm lower presses 1 mm in), or an
    /// MCAP bag of geometry_msgs/msg/PoseStamped tool poses (one marker per topic, each pose
    /// the centre of the marker's sphere, as the node's tools are).
    #[arg(long, conflicts_with = "udp")]
    markers: Option<PathBuf>,
    /// With an MCAP --markers file: the pose topics to use (default: every PoseStamped topic).
    #[arg(long, value_delimiter = ',')]
    marker_topics: Vec<String>,
    /// Listen for the seed's UDP marker frames (x, y in phyxels): a port (bound on loopback)
    /// or ADDR:PORT, an address other hosts can reach only when given one.
    #[arg(long, value_parser = udp_address)]
    udp: Option<SocketAddr>,
    /// Height of UDP markers' tips above the grid's plane (metres; default: the script's
    /// pressing depth below the rest height).
    #[arg(long)]
    udp_height: Option<f64>,
    /// World position of phyxel (0, 0) for motion files (default: the grid centred on the
    /// origin, in the xy plane).
    #[arg(long, value_delimiter = ',', num_args = 3)]
    origin: Option<Vec<f64>>,
    #[arg(long, default_value_t = 2000)]
    steps: u64,
    /// Pace the steps at dt (real time), as with a live marker stream.
    #[arg(long)]
    realtime: bool,
    /// Also write numbered frames every K steps.
    #[arg(long, default_value_t = 0)]
    every: u64,
    #[arg(long, value_delimiter = ',', default_value = "colour,bump,mesh,height")]
    render: Vec<Output>,
    /// Colour map (the configuration's when absent).
    #[arg(long, value_enum)]
    colormap: Option<CliColorMap>,
    /// Every S-th phyxel a vertex of the displacement mesh.
    #[arg(long, default_value_t = 2)]
    mesh_stride: usize,
    #[arg(long, default_value = "out/dpcm")]
    out: PathBuf,
    #[command(flatten)]
    backend: BackendArgs,
}

/// `PORT` → 127.0.0.1:PORT; anything else must be ADDR:PORT.
fn udp_address(text: &str) -> Result<SocketAddr, String> {
    match text.parse::<u16>() {
        Ok(port) => Ok(SocketAddr::from(([127, 0, 0, 1], port))),
        Err(_) => text.parse().map_err(|e| format!("`{text}` is neither a port nor ADDR:PORT ({e})")),
    }
}

/// Where this run's markers come from.
enum Source {
    Script,
    Motion(MotionFile, Calibration),
    Udp(UdpSource, f64),
}

pub fn run(args: DpcmArgs) -> Result<()> {
    let mut config = match &args.config {
        Some(path) => DpcmConfig::load(path)?,
        None => DpcmConfig::preset(&args.preset)?,
    };
    if let Some(size) = &args.size {
        let parsed: Option<(usize, usize)> =
            size.split_once('x').and_then(|(w, h)| Some((w.trim().parse().ok()?, h.trim().parse().ok()?)));
        let Some((w, h)) = parsed else { bail!("--size `{size}`: expected WxH, e.g. 1100x1100") };
        (config.width, config.height) = (w, h);
    }
    if let Some(map) = args.colormap {
        config.render.colormap = map.into();
    }
    let mut source = if let Some(path) = &args.markers {
        let calibration = match &args.origin {
            Some(o) => Calibration::new(Isometry3::translation(o[0], o[1], o[2]), config.spacing),
            None => Calibration::centred(&config),
        };
        let is_mcap = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
        // Tool poses are the centres of their tip spheres; a CSV row is a tip.
        let (motion, calibration) = match is_mcap {
            true => (load_mcap(path, &args.marker_topics)?, calibration),
            false => (MotionFile::load(path)?, calibration.at_tips(&config)),
        };
        warn_of_no_press(path, &motion, &calibration, &config);
        Source::Motion(motion, calibration)
    } else if let Some(addr) = args.udp {
        if !addr.ip().is_loopback() {
            tracing::warn!("listening for UDP markers on {addr}: reachable from other hosts");
        }
        let udp = UdpSource::bind(addr)?;
        tracing::info!(
            "listening for UDP marker frames on {}",
            udp.local_addr().map_or(addr.to_string(), |a| a.to_string())
        );
        let reach = config.marker.reach_below_centre();
        let centre = args.udp_height.map_or_else(|| config.script.pressing_height(&config), |tip| tip + reach);
        Source::Udp(udp, centre)
    } else {
        Source::Script
    };
    let mut engine = DpcmEngine::new(&config, &args.backend.choose_or(BackendChoice::Auto)?)?;
    tracing::info!("DPCM {}x{} on {}", config.width, config.height, engine.name());
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let progress = ProgressBar::new(args.steps).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} steps {per_sec} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut totals = StepStats::default();
    let started = Instant::now();
    for step in 0..args.steps {
        let t = step as f64 * config.dt;
        let markers: Vec<Marker> = match &mut source {
            Source::Script => config.script.markers_at(&config, t),
            Source::Motion(file, calibration) => file.markers_at(calibration, t),
            Source::Udp(udp, height) => udp.poll()?.map(|frame| frame.markers(*height)).unwrap_or_default(),
        };
        let stats = engine.step(&markers)?;
        totals.markers_applied += stats.markers_applied;
        totals.markers_dropped += stats.markers_dropped;
        totals.markers_off_grid += stats.markers_off_grid;
        if args.every > 0 && (step + 1) % args.every == 0 {
            write_outputs(&args, &config, &engine, Some(step + 1))?;
        }
        if args.realtime {
            let due = Duration::from_secs_f64((step + 1) as f64 * config.dt);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        progress.inc(1);
    }
    progress.finish_and_clear();
    let elapsed = started.elapsed().as_secs_f64();
    tracing::info!(
        "{} steps in {:.2} s ({:.0} steps/s); marker-steps applied {}, dropped {}, off the grid {}",
        args.steps,
        elapsed,
        args.steps as f64 / elapsed.max(1e-9),
        totals.markers_applied,
        totals.markers_dropped,
        totals.markers_off_grid
    );
    if let Source::Udp(udp, _) = &source {
        let c = udp.parser.counts;
        tracing::info!(
            "UDP frames: {} received, {} lost, {} malformed, {} out of order; {} steps left datagrams waiting (a flood)",
            c.received,
            c.lost,
            c.malformed,
            c.out_of_order,
            c.backlogged
        );
    }
    write_outputs(&args, &config, &engine, None)
}

/// A motion whose markers never reach below the rest height presses nothing; a centre below
/// it pushes the surface up around the marker (the seed's sphere repels to the nearer side).
fn warn_of_no_press(path: &std::path::Path, motion: &MotionFile, calibration: &Calibration, config: &DpcmConfig) {
    let centre = motion.lowest_centre(calibration);
    let lowest = centre - config.marker.reach_below_centre();
    if lowest >= config.rest_height {
        tracing::warn!(
            "{}: no marker reaches below the surface's rest height ({} m above the grid's plane; the lowest tip \
             is at {lowest:.4} m): nothing will be pressed",
            path.display(),
            config.rest_height
        );
    } else if centre < config.rest_height {
        tracing::warn!(
            "{}: a marker's centre goes below the surface's rest height ({centre:.4} m against {} m): the surface \
             there is pushed up around it, not down",
            path.display(),
            config.rest_height
        );
    }
}

#[cfg(feature = "mcap")]
fn load_mcap(path: &std::path::Path, topics: &[String]) -> Result<MotionFile> {
    let (motion, counts) = defvol::record::bag::motion_from_bag(path, topics)?;
    tracing::info!(
        "{}: {} tool poses on {} as markers 0.., {} dropped",
        path.display(),
        counts.messages,
        counts.topics.join(", "),
        counts.dropped
    );
    Ok(motion)
}

#[cfg(not(feature = "mcap"))]
fn load_mcap(path: &std::path::Path, _: &[String]) -> Result<MotionFile> {
    bail!("{}: this defvol was built without the `mcap` feature", path.display())
}

fn write_outputs(args: &DpcmArgs, config: &DpcmConfig, engine: &DpcmEngine, frame: Option<u64>) -> Result<()> {
    let (heights, displacement) = engine.heights_and_displacement()?;
    let (w, h) = (config.width, config.height);
    let dir = match frame {
        Some(_) => args.out.join("frames"),
        None => args.out.clone(),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let name = |stem: &str, ext: &str| match frame {
        Some(n) => dir.join(format!("{stem}_{n:06}.{ext}")),
        None => dir.join(format!("{stem}.{ext}")),
    };
    for output in &args.render {
        let path = match output {
            Output::Colour => {
                let path = name("colour", "png");
                render::colour_map(&displacement, w, h, &config.render).write_png(&path)?;
                path
            }
            Output::Bump => {
                let path = name("bump", "png");
                render::bump_map(&displacement, w, h, config.spacing, &config.render).write_png(&path)?;
                path
            }
            Output::Mesh => {
                let path = name("surface", "vtu");
                let mesh = render::displacement_mesh(&heights, &displacement, w, h, config.spacing, args.mesh_stride);
                defvol::io::write_triangles(&path, &mesh.positions, &mesh.triangles, Some(&mesh.scalars))?;
                path
            }
            Output::Height => {
                let path = name("height", "mha");
                render::write_height(&path, &heights, w, h, config.spacing)?;
                path
            }
        };
        if frame.is_none() {
            tracing::info!("wrote {}", path.display());
        }
    }
    Ok(())
}
