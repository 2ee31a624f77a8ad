//! The command line's names for the library's choices: the library's types carry no CLI
//! derives, so each has a mirror here that clap lists in `--help` and maps onto it.

use defvol::backend::BackendChoice;
use defvol::bench::dpcm::Physics;
use defvol::dpcm::render::ColorMap;
use defvol::dpcm::Topology;
use defvol::render::volume::{Mode, Shading};
use defvol::solver::{Integrator, Preconditioner};
use defvol::warp::{Sampling, Scheme};

/// A clap value enum mirroring a library enum variant for variant, and its conversion.
macro_rules! choice {
    ($(#[$doc:meta])* $cli:ident => $lib:ident { $($(#[$vdoc:meta])* $variant:ident),+ $(,)? }) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        pub enum $cli {
            $($(#[$vdoc])* $variant),+
        }

        impl From<$cli> for $lib {
            fn from(choice: $cli) -> Self {
                match choice {
                    $($cli::$variant => $lib::$variant),+
                }
            }
        }
    };
}

choice!(
    /// Where the stages run.
    CliBackend => BackendChoice {
        /// The GPU when a usable adapter exists, else the CPU.
        Auto,
        Cpu,
        /// The GPU, or an error naming why it cannot be used.
        Gpu,
    }
);
choice!(CliIntegrator => Integrator { ExplicitEuler, Verlet, VelocityVerlet, ImplicitEuler });
choice!(CliPreconditioner => Preconditioner {
    /// Inverse 3x3 diagonal blocks: cheap, on both backends.
    BlockJacobi,
    /// Smoothed-aggregation multigrid (CPU).
    Amg,
    /// Block Jacobi while CG converges quickly, then multigrid.
    Auto,
});
choice!(CliScheme => Scheme { Spans, Culling, Bbox });
choice!(CliSampling => Sampling {
    Trilinear,
    /// Catmull-Rom cubic convolution: sharper, about 4-8x the cost.
    Tricubic,
});
choice!(CliMode => Mode { Composite, Mip, Iso });
choice!(CliShading => Shading {
    None,
    /// Central-difference gradients, two-sided Lambert.
    Gradient,
    /// One extra sample toward the light (seed 002).
    ForwardDifference,
});
choice!(CliTopology => Topology { None, Four, Eight, Diagonal });
choice!(CliColorMap => ColorMap { Viridis, Magma, Inferno, Plasma, Turbo, Cividis, Greys, RedBlue, BrownGreen });
choice!(CliPhysics => Physics { Elastic, Plastic });

/// Every mirror's values from a comma list.
pub fn all<C: Copy + Into<L>, L>(choices: &[C]) -> Vec<L> {
    choices.iter().map(|c| (*c).into()).collect()
}
