//! The `biscale` command line: a thin layer over the library.

use biscale::bvndf::BvndfConfig;
use biscale::forward::{ForwardJob, Method};
use biscale::library::progress::Progress;
use biscale::material::MATERIAL_GRAMMAR;
use biscale::solve::Final;
use clap::{Parser, Subcommand, ValueEnum};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "biscale",
    version,
    about = "Inverse bi-scale material design for fabrication"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

/// A clap value parser: a number (`f64`) or a whole number (`usize`) in `[lo, hi]`, so that a
/// bad option fails before any work (instead of an empty answer, or a clamped value the user
/// did not ask for). NaN and infinities fail the range test of a finite range.
fn in_range<T>(lo: T, hi: T) -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync
where
    T: std::str::FromStr + PartialOrd + std::fmt::Display + Copy + Send + Sync,
{
    move |s: &str| match s.trim().parse::<T>() {
        Ok(v) if (lo..=hi).contains(&v) => Ok(v),
        _ => Err(format!("expected a number in [{lo}, {hi}], got '{s}'")),
    }
}

/// The compact BVNDF's build settings, shared by `forward` and `bench accuracy`; the defaults
/// are `forward`'s ([`BvndfConfig::forward`]).
#[derive(clap::Args)]
struct BvndfArgs {
    /// Sub-lobes per curved cluster, used with glossy materials (1: one vMF per cluster, as the
    /// libraries store; faster, less accurate on rough surfaces).
    #[arg(long, default_value_t = BvndfConfig::forward().sub_lobes as u16, value_parser = clap::value_parser!(u16).range(1..=64))]
    sub_lobes: u16,
    /// Normal clusters (vMF lobes per direction pair; 16 in the libraries: half the memory and
    /// evaluation time, less accurate on tall rough surfaces). `--lobes` is an alias.
    #[arg(long, alias = "lobes", default_value_t = BvndfConfig::forward().clusters as u16, value_parser = clap::value_parser!(u16).range(1..=64))]
    clusters: u16,
    /// Polar nodes of the direction grid, the last three beyond 88.5° when --last-theta is (10
    /// to 88.5° in the libraries: a build about 3× shorter, less accurate at grazing angles on
    /// tall grooves; 16: 1.7× shorter, a third of the memory).
    #[arg(long, default_value_t = BvndfConfig::forward().n_theta as u16, value_parser = clap::value_parser!(u16).range(2..=64))]
    n_theta: u16,
    /// Azimuths of the direction grid (16 is the libraries' grid: a build many times shorter, less
    /// accurate at grazing angles along grooves; 32, an earlier default: up to 60 % shorter,
    /// tall bumps at grazing views 3.1 % from the exact method up to 85° instead of 2.5 %).
    #[arg(long, default_value_t = BvndfConfig::forward().n_phi as u16, value_parser = clap::value_parser!(u16).range(3..=128))]
    n_phi: u16,
    /// Points spread over the surface for the pair table (about; at least one per facet), each
    /// with one horizon march per azimuth that serves every direction (16,384 in the
    /// libraries' grid).
    #[arg(long, default_value_t = BvndfConfig::forward().points as u32, value_parser = clap::value_parser!(u32).range(1..=16_777_216))]
    points: u32,
    /// First hits per grid direction for the area seen from it, without horizon marches, by
    /// line sweeps (a control variate for the pair table at grazing views, and the fine seen
    /// table's rows; at most 16 per heightmap cell are cast; 0: off, with the seen table, as in
    /// the libraries).
    #[arg(long, default_value_t = BvndfConfig::forward().seen_rays as u32, value_parser = clap::value_parser!(u32).range(0..=1_048_576))]
    seen_rays: u32,
    /// Azimuths of the fine table of the area seen from each direction (first hits only, one
    /// row per direction), which rescales the pair table where what a grazing view sees changes
    /// faster with its azimuth than `--n-phi` resolves (rows of bumps; rounded up to a multiple
    /// of `--n-phi`, 520 by default; at most `--n-phi`: off, as in the libraries).
    #[arg(long, default_value_t = BvndfConfig::forward().seen_phi as u32, value_parser = clap::value_parser!(u32).range(0..=4096))]
    seen_phi: u32,
    /// Height bands of the fine table's model of joint visibility (what is seen low between
    /// bumps is lit less than their tops; 1: the view and the light independent).
    #[arg(long, default_value_t = BvndfConfig::forward().seen_bands as u32, value_parser = clap::value_parser!(u32).range(1..=64))]
    seen_bands: u32,
    /// The last polar node of the direction grid, in degrees, 45 to 89.99 (above 88.5 the last
    /// three nodes are spaced evenly in the ray slope from 88.5° to it; views beyond it take its
    /// data; 88.5 in the libraries).
    #[arg(long, default_value_t = BvndfConfig::forward().last_theta_deg, value_parser = last_theta)]
    last_theta: f64,
}

fn last_theta(s: &str) -> std::result::Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (45.0..=89.99).contains(&v) => Ok(v),
        Ok(v) => Err(format!("{v} is not in 45..=89.99 (degrees)")),
        Err(e) => Err(format!("{e}; expected degrees in 45..=89.99")),
    }
}

impl BvndfArgs {
    fn config(&self) -> BvndfConfig {
        BvndfConfig {
            n_theta: self.n_theta as usize,
            n_phi: self.n_phi as usize,
            clusters: self.clusters as usize,
            points: self.points as usize,
            sub_lobes: self.sub_lobes as usize,
            seen_rays: self.seen_rays as usize,
            seen_phi: self.seen_phi as usize,
            seen_bands: self.seen_bands as usize,
            last_theta_deg: self.last_theta,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    Exact,
    Fast,
}

#[derive(Subcommand)]
enum Cmd {
    /// The main job: find details that reproduce a target look and that your shop can make,
    /// and export them (STL, heightmap PNG, summary.json, report) to outputs/<scene>/.
    #[command(after_help = design_help())]
    Design {
        /// Scene TOML (see `biscale design --help` and the user guide); default: built-in scene.
        scene: Option<PathBuf>,
        /// Where scene outputs go.
        #[arg(long, default_value = "outputs")]
        outputs: PathBuf,
        /// Replace an existing outputs/<scene>/ (only after the new one is complete).
        #[arg(long)]
        force: bool,
        /// Library directory; default: the cached build of the scene's library_profile.
        #[arg(long)]
        library: Option<PathBuf>,
        #[arg(long)]
        cache_dir: Option<PathBuf>,
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Large-scale fbar of one small-scale geometry and material at given direction pairs.
    #[command(after_help = forward_help(), allow_negative_numbers = true)]
    Forward {
        /// Heightmap file (.npy H×W of floats or integers, 8/16-bit grey .png, or an .obj of one
        /// period in mm, resampled to 128 samples along x) or a procedural spec
        /// such as 'vgroove:period=16,depth=4' (see below).
        #[arg(long, short = 'g', default_value = "bumps")]
        geometry: String,
        /// Small-scale material spec (see below).
        #[arg(long, short = 'm', default_value = "ggx:alpha=0.2+lambert:albedo=0.3")]
        material: String,
        /// CSV with header theta_i,phi_i,theta_o,phi_o (degrees). Default: the built-in 490 pairs.
        #[arg(long, short = 'p')]
        pairs: Option<PathBuf>,
        #[arg(long, value_enum, default_value = "fast")]
        method: MethodArg,
        /// Output CSV (written atomically). Default, or `-`: standard output.
        #[arg(long, short = 'o')]
        out: Option<PathBuf>,
        /// Physical side of one heightmap period in mm.
        #[arg(long, default_value_t = 10.0)]
        patch_size: f64,
        /// Multiplies stored heights (file values × scale = mm).
        #[arg(long, default_value_t = 1.0)]
        height_scale: f64,
        /// Exact method: view rays per cell side (s² rays through each heightmap cell; its noise
        /// on sharp lobes falls as this grows, the cost grows with its square). Default: 2, raised
        /// (up to 8) until the estimated error is within --exact-tol
        #[arg(long, value_parser = in_range::<usize>(1, 16))]
        exact_samples: Option<usize>,
        /// Exact method without --exact-samples: the estimated relative RMS error to reach (from
        /// the difference of its two one-sided estimates; 0.005 = 0.5 %)
        #[arg(long, default_value_t = biscale::forward::DEFAULT_EXACT_TOL, value_parser = in_range::<f64>(1e-4, 0.5))]
        exact_tol: f64,
        /// Fast method: the compact BVNDF's build.
        #[command(flatten)]
        build: BvndfArgs,
        /// No progress log on standard error.
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Find small-scale geometry and/or material that reproduce a target large-scale look.
    #[command(allow_negative_numbers = true)]
    Solve {
        /// Target look: any material spec, 'ward:ax=0.30,ay=0.08', or a MERL .binary path.
        #[arg(long, short = 't', default_value = "ward:ax=0.30,ay=0.08")]
        target: String,
        /// Brightness edit (factor, Sec. 7).
        #[arg(long, default_value_t = 1.0, value_parser = in_range(1e-6, 1e6))]
        brightness: f64,
        /// Contrast edit (Eq. 16).
        #[arg(long, default_value_t = 1.0, value_parser = in_range(0.0, 1e3))]
        contrast: f64,
        /// Angular edit: blur (> 1) or sharpen (< 1) the highlight, S or SX,SY (stretch).
        #[arg(long, default_value = "1")]
        blur: String,
        /// Target colour r,g,b (average fbar per channel); default: the target material's own.
        #[arg(long)]
        colour: Option<String>,
        /// Make the target a bi-scale combination: this geometry (procedural spec or heightmap,
        /// read as --fix-geometry) under the --target material, by the fast forward model (the
        /// values of `biscale forward --geometry G --material M`); for validation. Only
        /// --brightness and --colour edit it.
        #[arg(long)]
        target_geometry: Option<String>,
        /// Fix the material (spec) and solve for the geometry.
        #[arg(long)]
        fix_material: Option<String>,
        /// Fix the geometry (procedural spec or heightmap) and solve for the material.
        #[arg(long)]
        fix_geometry: Option<String>,
        /// Rotations of the geometry tried (geometry and general solvers).
        #[arg(long, default_value_t = 4, value_parser = in_range::<usize>(1, 360))]
        psi: usize,
        /// Candidates returned.
        #[arg(long, short = 'k', default_value_t = 5, value_parser = in_range::<usize>(1, 1000))]
        k: usize,
        /// Items re-ranked with their own library data [default: geometries one per 20 (256 to 4096), materials one per 4 (64 to 1024)]
        #[arg(long, value_parser = in_range::<usize>(1, 100_000_000))]
        pool: Option<usize>,
        /// Geometry solver: rank the library by the representatives' light lobes only, not also
        /// by their binned columns (the pool then comes from the light-lobe rankings: X and, when the library has them, the weights refitted to the light lobes).
        #[arg(long)]
        lobes_search_only: bool,
        /// Geometry solver: when the pool's best is over 1 %, re-rank up to N more pools from the
        /// search's ranking, while each finds a geometry at under half the error (0: the pool
        /// only). The general
        /// solver widens one last geometry solve, with the best material found
        #[arg(long, default_value_t = biscale::solve::geometry::WIDEN)]
        widen: usize,
        /// General solver: starts (plus three from the first start's material sharpened, lobe
        /// widths x 0.7, x 0.4 and x 0.25, each run only while nothing found is within 7 %, or
        /// always with --stop-below 0) and iterations per start.
        #[arg(long, default_value_t = 5, value_parser = in_range::<usize>(1, 1000))]
        starts: usize,
        #[arg(long, default_value_t = 4, value_parser = in_range::<usize>(1, 1000))]
        iterations: usize,
        /// General solver: geometries of each geometry solve that get a material solve.
        #[arg(long, default_value_t = 3, value_parser = in_range::<usize>(1, 1000))]
        beam: usize,
        /// General solver: pairs of the joint search (both libraries through their
        /// representatives) re-ranked with their own data (more than 32 narrowed by coarse
        /// passes first); the best pairs' materials are the starts. 0: flat-patch and random
        /// starts only.
        #[arg(long, default_value_t = 1024)]
        joint_pool: usize,
        /// General solver: stop once a combination is within this relative error (0.01 = 1 %;
        /// 0: run every start and iteration), after the iteration that found it, or at once
        /// when it is within 0.01 % (the look itself).
        #[arg(long, default_value_t = biscale::solve::general::STOP_BELOW, value_parser = in_range(0.0, 1.0))]
        stop_below: f64,
        /// Weight of the colour term (Eq. 13), 0..1.
        #[arg(long, default_value_t = 0.0, value_parser = in_range(0.0, 1.0))]
        beta: f64,
        /// Final evaluation of the K candidates.
        #[arg(long, value_enum, default_value = "exact")]
        final_eval: FinalArg,
        /// Visually equivalent details: return up to N diverse combinations within --bound.
        #[arg(long, value_parser = in_range::<usize>(1, 1000))]
        veds: Option<usize>,
        #[arg(long, default_value_t = 0.07, value_parser = in_range(1e-6, 10.0))]
        bound: f64,
        /// Library directory; default: the cached build of --profile (built on first use).
        #[arg(long)]
        library: Option<PathBuf>,
        #[arg(long, default_value = "default")]
        profile: String,
        #[arg(long)]
        cache_dir: Option<PathBuf>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// The paper's Table 1 protocol on random library combinations, and error against run time.
    Validate {
        /// Library directory; default: the cached build of --profile.
        #[arg(long)]
        library: Option<PathBuf>,
        #[arg(long, default_value = "default")]
        profile: String,
        #[arg(long)]
        cache_dir: Option<PathBuf>,
        #[arg(long, default_value_t = 20, value_parser = in_range::<usize>(1, 1_000_000))]
        cases: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        #[arg(long, default_value_t = 1, value_parser = in_range::<usize>(1, 360))]
        psi: usize,
        /// Items re-ranked with their own library data [default: geometries one per 20 (256 to 4096), materials one per 4 (64 to 1024)]
        #[arg(long, value_parser = in_range::<usize>(1, 100_000_000))]
        pool: Option<usize>,
        /// Geometry solver: rank the library by the representatives' light lobes only, not also
        /// by their binned columns (the pool then comes from the light-lobe rankings: X and, when the library has them, the weights refitted to the light lobes).
        #[arg(long)]
        lobes_search_only: bool,
        /// Geometry solver: when the pool's best is over 1 %, re-rank up to N more pools from the
        /// search's ranking, while each finds a geometry at under half the error (0: the pool
        /// only). The general
        /// solver widens one last geometry solve, with the best material found
        #[arg(long, default_value_t = biscale::solve::geometry::WIDEN)]
        widen: usize,
        /// Candidates each solver returns: the best K by library data, which stage 3
        /// (--final-eval) re-evaluates.
        #[arg(long, default_value_t = 5, value_parser = in_range::<usize>(1, 1000))]
        k: usize,
        /// General solver: starts (plus three from the first start's material sharpened, lobe
        /// widths x 0.7, x 0.4 and x 0.25, each run only while nothing found is within 7 %, or
        /// always with --stop-below 0).
        #[arg(long, default_value_t = 3, value_parser = in_range::<usize>(1, 1000))]
        starts: usize,
        /// General solver: geometries of each geometry solve that get a material solve.
        #[arg(long, default_value_t = 3, value_parser = in_range::<usize>(1, 1000))]
        beam: usize,
        /// General solver: pairs of the joint search (both libraries through their
        /// representatives) re-ranked with their own data (more than 32 narrowed by coarse
        /// passes first); the best pairs' materials are the starts. 0: flat-patch and random
        /// starts only.
        #[arg(long, default_value_t = 1024)]
        joint_pool: usize,
        /// General solver: stop once a combination is within this relative error (0.01 = 1 %;
        /// 0: run every start and iteration), after the iteration that found it, or at once
        /// when it is within 0.01 % (the look itself).
        #[arg(long, default_value_t = biscale::solve::general::STOP_BELOW, value_parser = in_range(0.0, 1.0))]
        stop_below: f64,
        /// Solvers to run, comma-separated (each with its exhaustive scan) [default: all]
        #[arg(long, value_delimiter = ',')]
        solvers: Vec<SolverArg>,
        /// Leave out the exhaustive scans (every library item with its own data; seconds per
        /// case on a large library), and with them the count of cases in which each solver found
        /// the scan's optimum.
        #[arg(long)]
        no_exhaustive: bool,
        /// Also sweep the geometry solver's accuracy knobs (error against run time).
        #[arg(long)]
        sweep: bool,
        /// Write the sweep as a PNG plot.
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Targets are the combinations as the library represents them (its light lobes and
        /// tables), and answers are judged with the same data: the paper's protocol. Default:
        /// targets from the full forward model, answers verified with it. Needs --psi 1.
        #[arg(long)]
        library_targets: bool,
        /// Stage 3 of every solver, timed: `fast` and `exact` re-evaluate the best K (--k) by
        /// library data with the fast forward model (the targets' model) or the exact evaluator
        /// and answer the best of them, as `biscale solve` does; `library` answers the best by
        /// library data. [default: fast; library with --library-targets, the only one allowed
        /// there]
        #[arg(long, value_enum)]
        final_eval: Option<FinalArg>,
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Build, merge, describe and check precomputed libraries of geometries and materials.
    Library {
        #[command(subcommand)]
        what: LibraryCmd,
    },
    /// Benchmarks and accuracy tables of the forward model (prints Markdown tables).
    Bench {
        #[command(subcommand)]
        what: BenchCmd,
        /// No progress on standard error (the tables still go to standard output).
        #[arg(long, short = 'q', global = true)]
        quiet: bool,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum SolverArg {
    Geometry,
    Material,
    General,
}

impl From<SolverArg> for biscale::validate::Solver {
    fn from(s: SolverArg) -> Self {
        match s {
            SolverArg::Geometry => Self::Geometry,
            SolverArg::Material => Self::Material,
            SolverArg::General => Self::General,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum FinalArg {
    Exact,
    Fast,
    Library,
}

impl From<FinalArg> for Final {
    fn from(f: FinalArg) -> Final {
        match f {
            FinalArg::Exact => Final::Exact,
            FinalArg::Fast => Final::Fast,
            FinalArg::Library => Final::Library,
        }
    }
}

#[derive(Subcommand)]
enum LibraryCmd {
    /// Build a library from a profile (profiles/library/<name>.toml or a path), whole or one shard.
    Build {
        /// Profile name (a file of profiles/library/: tiny, default, paper16, paper4, paper2, paper-materials, paper) or
        /// path to a profile TOML.
        #[arg(long, default_value = "default")]
        profile: String,
        /// Output directory (default: the cache entry of the profile).
        #[arg(long, short = 'o')]
        out: Option<PathBuf>,
        /// Cache root (default: $BISCALE_CACHE, $XDG_CACHE_HOME/biscale or ~/.cache/biscale).
        #[arg(long)]
        cache_dir: Option<PathBuf>,
        /// Build only shard i of N (0-based, e.g. 3/8); then run `biscale library merge DIR`.
        #[arg(long)]
        shard: Option<String>,
        /// Write per-chunk files and keep them after the merge (without it, a one-process build
        /// writes each chunk straight into the library's arrays; a shard always writes chunk files).
        #[arg(long)]
        keep_chunks: bool,
        /// Rebuild even if the directory already holds this finished library.
        #[arg(long)]
        force: bool,
        /// No progress bars or log lines.
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Join the shards in a build directory, compress, pick representatives, write the manifest.
    Merge {
        dir: PathBuf,
        #[arg(long)]
        keep_chunks: bool,
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Fit a finished library's geometry weights to its light lobes (geometry/x-lobes.bsa) and
    /// write the material solver's finer representatives (material/search-*.bsa), for libraries
    /// built before the merge did; rewrites the manifest.
    Refit {
        dir: PathBuf,
        /// Set the library profile's `compression.material_search_energy` first (e.g. 0.99999, as
        /// the shipped profiles have it; the library's profile.toml is rewritten). Without it,
        /// the library's own profile decides (no key: no finer selection).
        #[arg(long)]
        material_search_energy: Option<f64>,
        /// First store f32 light-lobe records in half precision, as `geometry.lobe_precision =
        /// "half"` (the default since it exists) builds them: half the bytes, the same files as
        /// such a build. Sets that key of the library's profile.
        #[arg(long)]
        half_lobes: bool,
        /// Store the half-precision light-lobe records packed: the same numbers without the
        /// blocks that are zero and the zenith's repeated view nodes (52 % of the bytes on
        /// `paper`), for libraries whose records do not fit in memory. Lossless: every record
        /// is checked to unpack to itself.
        #[arg(long)]
        pack_lobes: bool,
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Print a library's counts, compression and build times.
    Info { dir: PathBuf },
    /// Check every file of a library against its manifest's checksums.
    Verify { dir: PathBuf },
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Time to build the compact BVNDF and the prefiltered material, and to evaluate 490 pairs.
    Speed {
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 5, value_parser = in_range::<usize>(1, 100_000))]
        reps: usize,
    },
    /// Precompute time per library geometry and material, extrapolated to a whole profile.
    LibrarySpeed {
        #[arg(long, default_value = "paper")]
        profile: String,
        /// Geometries timed (a quarter as many materials).
        #[arg(long, default_value_t = 64, value_parser = in_range::<usize>(1, 1_000_000))]
        sample: usize,
    },
    /// The compressed search on a library of the paper's size (synthetic weights) against the
    /// memory bandwidth.
    Scan {
        /// Library items (the paper's geometry library: 164,431).
        #[arg(long, default_value_t = 164_431)]
        items: usize,
        /// Representatives (the default library's geometry library: 74).
        #[arg(long, default_value_t = 74, value_parser = in_range::<usize>(1, 100_000))]
        reps: usize,
        /// Samples (7 lights × 70 views).
        #[arg(long, default_value_t = 490)]
        samples: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// fbar from a library's representatives (Eq. 12) against the exact evaluator.
    LibraryAccuracy {
        /// Library directory (built by `biscale library build`).
        dir: PathBuf,
        #[arg(long, default_value_t = 200, value_parser = in_range::<usize>(1, 1_000_000))]
        geometries: usize,
        #[arg(long, default_value_t = 10, value_parser = in_range::<usize>(1, 1_000_000))]
        materials: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// The fabrication stage: milling simulation and detail check of 128² generators, and
    /// exports of 50 × 50 mm tiles, with a fabrication profile.
    Fab {
        /// Fabrication profile (a shipped name or a TOML path).
        #[arg(long, default_value = "cnc-ball1-aluminium")]
        profile: String,
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 3, value_parser = in_range::<usize>(1, 100_000))]
        reps: usize,
    },
    /// The exact method's own error: its estimate, and its error against itself with many more
    /// rays, at 2 × 2 rays per cell and with `forward`'s automatic choice.
    Exact {
        /// A case 'GEOMETRY|MATERIAL' (repeatable); default: five sharp and broad cases.
        #[arg(long = "case")]
        cases: Vec<String>,
        /// View rays per cell side of the reference.
        #[arg(long, default_value_t = 16, value_parser = in_range::<usize>(1, 64))]
        reference: usize,
        /// Tolerance of the automatic choice on the estimated relative RMS error.
        #[arg(long, default_value_t = biscale::forward::DEFAULT_EXACT_TOL, value_parser = in_range::<f64>(1e-4, 0.5))]
        tol: f64,
    },
    /// Error of the fast evaluator against the exact one over random geometries and materials.
    Accuracy {
        #[arg(long, default_value_t = 24, value_parser = in_range::<usize>(1, 1_000_000))]
        cases: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Draw sharp materials (glossy widths 0.002–0.06 rad, which the fast method sums over
        /// facets) instead of the usual ones (widths from 0.08).
        #[arg(long)]
        sharp: bool,
        /// View rays per cell side of the exact reference (its noise on sharp lobes falls as
        /// this grows; the cost grows with its square).
        #[arg(long, default_value_t = 2, value_parser = in_range::<usize>(1, 64))]
        exact_samples: usize,
        /// Instead, the reference's rays chosen as `forward` chooses them, for this estimated
        /// relative RMS error (e.g. 0.005).
        #[arg(long, conflicts_with = "exact_samples", value_parser = in_range::<f64>(1e-4, 0.5))]
        exact_tol: Option<f64>,
        /// The compact BVNDF's build.
        #[command(flatten)]
        build: BvndfArgs,
    },
}

fn design_help() -> String {
    format!(
        "THE BUILT-IN DEFAULT SCENE (copy it to a file and edit it)\n{}",
        biscale::design::scene::DEFAULT_SCENE
    )
}

fn forward_help() -> String {
    let gens: Vec<String> = biscale::generators::list()
        .iter()
        .map(|(n, h)| format!("  {n:<10} {h}"))
        .collect();
    format!(
        "MATERIALS\n{MATERIAL_GRAMMAR}\n\nGEOMETRY\nA heightmap file, or a procedural spec 'name:key=value,...':\n{}\n\n\
         OUTPUT\ntheta_i,phi_i,theta_o,phi_o,fbar,brdf — fbar includes cos(theta_i); brdf = fbar / cos(theta_i).",
        gens.join("\n")
    )
}

/// Write a command's result to standard output. A closed pipe (`biscale … | head`) ends the
/// output quietly; any other failure (a full disk) is an error naming standard output.
fn emit(text: &str) -> biscale::Result<()> {
    use std::io::Write;
    let mut o = std::io::stdout().lock();
    match o.write_all(text.as_bytes()).and_then(|_| o.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(biscale::Error::new(
            "standard output",
            format!("cannot write: {e}"),
        )),
        _ => Ok(()),
    }
}

fn main() -> ExitCode {
    if let Err(e) = biscale::cpu::check() {
        biscale::library::progress::line(&format!("biscale: error: {e}"));
        return ExitCode::from(2);
    }
    // Before any other thread starts (the CPU check first: nothing before it may use the
    // instructions it checks for): an interrupted run removes its temporary files.
    biscale::interrupt::install();
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Design {
            scene,
            outputs,
            force,
            library,
            cache_dir,
            quiet,
        } => biscale::design::run(&biscale::design::DesignJob {
            scene,
            outputs,
            force,
            library,
            cache_dir,
            quiet,
        })
        .and_then(|t| emit(&t)),
        Cmd::Forward {
            geometry,
            material,
            pairs,
            method,
            out,
            patch_size,
            height_scale,
            exact_samples,
            exact_tol,
            build,
            quiet,
        } => {
            // `--out -` is standard output, as when --out is left out.
            let out = out.filter(|p| p.as_os_str() != "-");
            let to_stdout = out.is_none();
            let job = ForwardJob {
                geometry,
                material,
                pairs,
                method: match method {
                    MethodArg::Exact => Method::Exact,
                    MethodArg::Fast => Method::Fast,
                },
                out,
                patch_size_mm: patch_size,
                height_scale,
                exact_samples,
                exact_tol,
                bvndf: build.config(),
                quiet,
                ..ForwardJob::default()
            };
            biscale::forward::run(&job).and_then(|r| if to_stdout { emit(&r.csv) } else { Ok(()) })
        }
        Cmd::Solve {
            target,
            brightness,
            contrast,
            blur,
            colour,
            target_geometry,
            fix_material,
            fix_geometry,
            psi,
            k,
            pool,
            lobes_search_only,
            widen,
            starts,
            iterations,
            beam,
            joint_pool,
            stop_below,
            beta,
            final_eval,
            veds,
            bound,
            library,
            profile,
            cache_dir,
            seed,
            json,
            quiet,
        } => colour
            .as_deref()
            .map(biscale::solve::look::parse_colour)
            .transpose()
            .and_then(|c| biscale::solve::look::parse_blur(&blur).map(|b| (c, b)))
            .and_then(|(colour, blur)| {
                use biscale::solve::SolveOptions;
                biscale::solve::job::run(&biscale::solve::job::SolveJob {
                    target,
                    edits: biscale::solve::look::Edits {
                        brightness,
                        contrast,
                        blur,
                    },
                    colour,
                    target_geometry,
                    fix_material,
                    fix_geometry,
                    options: SolveOptions {
                        k: k.max(1),
                        pool: pool.map_or(0, |p| p.max(1)),
                        binned_search: !lobes_search_only,
                        widen,
                        psi: psi.max(1),
                        beta,
                        final_eval: final_eval.into(),
                        sampling: biscale::sampling::SamplingConfig {
                            seed,
                            ..Default::default()
                        },
                        ..SolveOptions::default()
                    },
                    general: biscale::solve::general::GeneralOptions {
                        starts: starts.max(1),
                        max_iterations: iterations.max(1),
                        seed,
                        start_material: None,
                        beam: beam.max(1),
                        joint_pool,
                        stop_below: stop_below.max(0.0),
                    },
                    veds: veds.map(|n| (n.max(1), bound)),
                    library,
                    profile,
                    cache_dir,
                    json,
                    quiet,
                })
            })
            .and_then(|t| emit(&t)),
        Cmd::Validate {
            library,
            profile,
            cache_dir,
            cases,
            seed,
            psi,
            pool,
            lobes_search_only,
            widen,
            k,
            starts,
            beam,
            joint_pool,
            stop_below,
            solvers,
            no_exhaustive,
            sweep,
            plot,
            library_targets,
            final_eval,
            quiet,
        } => {
            let progress = biscale::library::progress::Progress { quiet };
            biscale::solve::job::open_library(&library, &profile, &cache_dir, &progress)
                .and_then(|lib| {
                    biscale::validate::run(
                        &lib,
                        &biscale::validate::ValidateJob {
                            cases: cases.max(1),
                            seed,
                            options: biscale::solve::SolveOptions {
                                psi: psi.max(1),
                                pool: pool.map_or(0, |p| p.max(1)),
                                binned_search: !lobes_search_only,
                                widen,
                                k: k.max(1),
                                final_eval: match (final_eval, library_targets) {
                                    (Some(f), _) => f.into(),
                                    (None, false) => Final::Fast,
                                    (None, true) => Final::Library,
                                },
                                ..Default::default()
                            },
                            general: biscale::solve::general::GeneralOptions {
                                starts: starts.max(1),
                                seed,
                                beam: beam.max(1),
                                joint_pool,
                                stop_below: stop_below.max(0.0),
                                ..Default::default()
                            },
                            sweep: sweep || plot.is_some(),
                            plot,
                            quiet,
                            library_targets,
                            solvers: solvers.into_iter().map(Into::into).collect(),
                            exhaustive: !no_exhaustive,
                        },
                    )
                })
                .and_then(|t| emit(&t))
        }
        Cmd::Library { what } => match what {
            LibraryCmd::Build {
                profile,
                out,
                cache_dir,
                shard,
                keep_chunks,
                force,
                quiet,
            } => shard
                .as_deref()
                .map(biscale::library::build::Shard::parse)
                .unwrap_or(Ok(biscale::library::build::Shard::ALL))
                .and_then(|shard| {
                    biscale::library::commands::build(&biscale::library::commands::BuildJob {
                        profile,
                        out,
                        cache_dir,
                        shard,
                        quiet,
                        keep_chunks,
                        force,
                    })
                })
                .and_then(|t| emit(&t)),
            LibraryCmd::Merge {
                dir,
                keep_chunks,
                quiet,
            } => biscale::library::commands::merge(&dir, quiet, keep_chunks).and_then(|t| emit(&t)),
            LibraryCmd::Refit {
                dir,
                material_search_energy,
                half_lobes,
                pack_lobes,
                quiet,
            } => biscale::library::commands::refit(
                &dir,
                material_search_energy,
                half_lobes,
                pack_lobes,
                quiet,
            )
            .and_then(|t| emit(&t)),
            LibraryCmd::Info { dir } => {
                biscale::library::commands::info(&dir).and_then(|t| emit(&t))
            }
            LibraryCmd::Verify { dir } => {
                biscale::library::commands::verify(&dir).and_then(|t| emit(&t))
            }
        },
        Cmd::Bench { what, quiet } => match what {
            BenchCmd::Speed { reps } => {
                biscale::bench::speed(reps.max(1), &Progress { quiet }).and_then(|t| emit(&t))
            }
            BenchCmd::Scan {
                items,
                reps,
                samples,
                seed,
            } => biscale::solve::bench::scan(items, reps, samples, seed).and_then(|t| emit(&t)),
            BenchCmd::LibrarySpeed { profile, sample } => {
                biscale::library::bench::speed(&profile, sample.max(1), &Progress { quiet })
                    .and_then(|t| emit(&t))
            }
            BenchCmd::LibraryAccuracy {
                dir,
                geometries,
                materials,
                seed,
            } => biscale::library::bench::accuracy(
                &dir,
                geometries.max(1),
                materials.max(1),
                seed,
                &Progress { quiet },
            )
            .and_then(|t| emit(&t)),
            BenchCmd::Fab { profile, reps } => biscale::fab::profile::load_profile(
                &profile,
                &biscale::fab::profile::FabPaths::default_paths(),
            )
            .and_then(|p| biscale::fab::bench::bench_fab(&p, reps.max(1)))
            .and_then(|t| emit(&t)),
            BenchCmd::Exact {
                cases,
                reference,
                tol,
            } => {
                let cases: std::result::Result<Vec<(String, String)>, biscale::Error> =
                    if cases.is_empty() {
                        Ok(biscale::bench::EXACT_CASES
                            .iter()
                            .map(|(g, m)| (g.to_string(), m.to_string()))
                            .collect())
                    } else {
                        cases
                            .iter()
                            .map(|c| match c.split_once('|') {
                                Some((g, m)) => Ok((g.to_string(), m.to_string())),
                                None => Err(biscale::Error::new(
                                    "--case",
                                    format!("'{c}': expected GEOMETRY|MATERIAL"),
                                )),
                            })
                            .collect()
                    };
                cases.and_then(|c| {
                    biscale::bench::exact(&c, reference, tol, &Progress { quiet })
                        .and_then(|t| emit(&t))
                })
            }
            BenchCmd::Accuracy {
                cases,
                seed,
                sharp,
                exact_samples,
                exact_tol,
                build,
            } => {
                let cfg = build.config();
                let opt = biscale::bench::AccuracyOptions {
                    sharp,
                    exact_samples,
                    exact_tol,
                };
                biscale::bench::accuracy(cases.max(1), seed, &cfg, &opt, &Progress { quiet })
                    .and_then(|t| emit(&t))
            }
        },
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            biscale::library::progress::line(&format!("biscale: error: {e}"));
            ExitCode::from(2)
        }
    }
}
