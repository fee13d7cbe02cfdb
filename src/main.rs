//! The `photostereo` binary: reconstruct a folder, render the project's data sets, or
//! serve the HTTP API.

mod bench;
mod cli;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use cli::calibrate::{CalibrateArgs, calibrate};
use cli::evaluate::{evaluate, evaluate_holdout, render};
use cli::flags::kebab;
use cli::integrate::{IntegrateArgs, integrate};
use cli::reconstruct::{ReconstructArgs, reconstruct};
use photostereo::core::options::Integration;
use photostereo::service;

#[derive(Parser)]
#[command(
    name = "photostereo",
    version,
    about = "Photometric stereo: albedo, normals, heights and meshes from images under known lights"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// Parsed once at start: the serve flags' size costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// Run the HTTP service.
    Serve(service::ServeArgs),
    /// Print the OpenAPI document (the committed copy is openapi/openapi.json).
    Openapi,
    /// Exit 0 when the service answers its health URL (for container HEALTHCHECKs).
    Healthcheck(service::HealthcheckArgs),
    /// Reconstruct a folder: images with light_directions.csv (or .json), or the benchmark
    /// layout (light_directions.txt, filenames.txt, light_intensities.txt, mask.png).
    Reconstruct(ReconstructArgs),
    /// Integrate a normal map (PNG or EXR) into heights, or into depth under a pinhole
    /// camera: height/depth maps, mesh, point cloud and result.json, as `reconstruct`'s.
    Integrate(IntegrateArgs),
    /// Measure the lights from a chrome sphere: one image of a mirror ball per light in
    /// <dir> (every image file, in name order) → a light table `reconstruct` reads.
    Calibrate(CalibrateArgs),
    /// Render the project's own data sets, with ground truth, into a folder (e.g. res/).
    Render {
        /// Output folder; one sub-folder per data set.
        dir: PathBuf,
        /// Render only these sets (default: all).
        #[arg(long, value_delimiter = ',')]
        only: Vec<String>,
    },
    /// Score every solver on each data set with ground truth (a folder like res/) and
    /// print a Markdown table: angular error, depth error (MAE and RMS after the median
    /// offset, or under the set's camera the median scale: MADE), solve time. With
    /// --holdout-lights, score them on one capture without ground truth instead.
    Evaluate {
        dir: PathBuf,
        /// Integration method for the depth column.
        #[arg(long, value_parser = kebab::<Integration>, default_value = "robust-poisson")]
        integration: Integration,
        /// `dir` is one capture (any folder `reconstruct` reads): reconstruct it from
        /// three quarters of its lights, four times over, and report how well each
        /// solver predicts the images it was not given (median relative error).
        #[arg(long)]
        holdout_lights: bool,
    },
    /// Time the core (decode, full job, each stage), its peak memory and, with --http /
    /// --load, the in-process HTTP service on rendered data sets; prints Markdown tables.
    Bench(bench::BenchArgs),
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?)
}

/// A command whose output is read from a pipe ends quietly when the reader stops reading
/// (`photostereo evaluate res | head`), as Unix tools do, instead of panicking on the
/// broken pipe: Rust ignores SIGPIPE by default. Each of these commands writes its files
/// before it prints, so nothing is lost. The commands that talk over sockets (the server,
/// its health check, the bench) keep ignoring it.
fn end_quietly_on_a_closed_pipe(command: &Command) {
    if !matches!(
        command,
        Command::Serve(_) | Command::Healthcheck(_) | Command::Bench(_)
    ) {
        // SAFETY: restoring a signal's default disposition at start, before any thread.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    end_quietly_on_a_closed_pipe(&cli.command);
    let result = match cli.command {
        Command::Serve(args) => runtime().and_then(|rt| rt.block_on(service::serve(args))),
        Command::Openapi => {
            print!("{}", service::openapi_json());
            Ok(())
        }
        Command::Healthcheck(args) => {
            runtime().and_then(|rt| rt.block_on(service::healthcheck(&args.url)))
        }
        Command::Reconstruct(args) => reconstruct(args),
        Command::Integrate(args) => integrate(args),
        Command::Calibrate(args) => calibrate(args),
        Command::Render { dir, only } => render(dir, only),
        Command::Evaluate {
            dir,
            holdout_lights: true,
            ..
        } => evaluate_holdout(dir),
        Command::Evaluate {
            dir, integration, ..
        } => evaluate(dir, integration),
        Command::Bench(args) => bench::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
