//! The `biscale` command line: a thin layer over the library.

use biscale::bvndf::BvndfConfig;
use biscale::forward::{ForwardJob, Method};
use biscale::material::MATERIAL_GRAMMAR;
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

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    Exact,
    Fast,
}

#[derive(Subcommand)]
enum Cmd {
    /// Large-scale fbar of one small-scale geometry and material at given direction pairs.
    #[command(after_help = forward_help())]
    Forward {
        /// Heightmap file (.npy float32/float64 H×W, 8/16-bit grey .png) or a procedural spec
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
        /// Output CSV (written atomically). Default: standard output.
        #[arg(long, short = 'o')]
        out: Option<PathBuf>,
        /// Physical side of one heightmap period in mm.
        #[arg(long, default_value_t = 10.0)]
        patch_size: f64,
        /// Multiplies stored heights (file values × scale = mm).
        #[arg(long, default_value_t = 1.0)]
        height_scale: f64,
        /// Exact method: points per facet side (s² visibility samples per facet).
        #[arg(long, default_value_t = 2)]
        exact_samples: usize,
        /// Fast method: normal clusters (vMF lobes per direction pair).
        #[arg(long, default_value_t = 16)]
        lobes: usize,
        /// No progress log on standard error.
        #[arg(long, short = 'q')]
        quiet: bool,
    },
    /// Benchmarks and accuracy tables of the forward model (prints Markdown tables).
    Bench {
        #[command(subcommand)]
        what: BenchCmd,
    },
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Time to build the compact BVNDF and the prefiltered material, and to evaluate 490 pairs.
    Speed {
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 5)]
        reps: usize,
    },
    /// Error of the fast evaluator against the exact one over random geometries and materials.
    Accuracy {
        #[arg(long, default_value_t = 24)]
        cases: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
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

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Forward {
            geometry,
            material,
            pairs,
            method,
            out,
            patch_size,
            height_scale,
            exact_samples,
            lobes,
            quiet,
        } => {
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
                exact_samples: exact_samples.clamp(1, 16),
                bvndf: BvndfConfig {
                    clusters: lobes.clamp(1, 64),
                    ..BvndfConfig::default()
                },
                quiet,
                ..ForwardJob::default()
            };
            biscale::forward::run(&job).map(|r| {
                if to_stdout {
                    print!("{}", r.csv);
                }
            })
        }
        Cmd::Bench { what } => match what {
            BenchCmd::Speed { reps } => biscale::bench::speed(reps.max(1)).map(|t| print!("{t}")),
            BenchCmd::Accuracy { cases, seed } => {
                biscale::bench::accuracy(cases.max(1), seed).map(|t| print!("{t}"))
            }
        },
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("biscale: error: {e}");
            ExitCode::from(2)
        }
    }
}
