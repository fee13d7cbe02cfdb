//! The `bench` subcommand's flags and the values it accepts.

use std::path::PathBuf;

use anyhow::ensure;
use clap::Args;

/// Time, memory and HTTP figures on synthetic data sets (docs/benchmarks.md holds them).
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Square image sizes in pixels, comma-separated (up to 8192; 5120² is a 26-megapixel camera).
    #[arg(long, value_delimiter = ',', default_value = "512,1024,2048")]
    pub sizes: Vec<usize>,
    /// Lights (= 16-bit PNG images) per data set.
    #[arg(long, default_value_t = 24)]
    pub lights: usize,
    /// Runs of each measurement; the tables show medians (peak memory: the largest).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Also submit every set to an in-process server over HTTP and time it.
    #[arg(long)]
    pub http: bool,
    /// With --http: also run every HTTP job on a second in-process server that keeps its
    /// jobs in this PostgreSQL database (`postgres://…`) and its files in --store,
    /// alternating with the SQLite + data directory server, and compare the two.
    #[arg(long, requires_all = ["http", "store"])]
    pub database_url: Option<String>,
    /// The second server's store, `s3://bucket[/prefix]` (S3 settings from AWS_ENDPOINT_URL,
    /// AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION, AWS_ALLOW_HTTP).
    #[arg(long, requires = "database_url")]
    pub store: Option<String>,
    /// With --database-url: processes (with their children) whose CPU time over each
    /// PostgreSQL + S3 job is shown beside the job's, e.g. the S3 server and PostgreSQL's
    /// postmaster when they share the machine.
    #[arg(long, value_delimiter = ',', requires = "database_url")]
    pub server_pids: Vec<u32>,
    /// Also time status requests while every server worker is busy with a big job.
    #[arg(long)]
    pub load: bool,
    /// Status requests sent by --load.
    #[arg(long, default_value_t = 1000)]
    pub requests: usize,
    /// Keep-alive connections the --load status requests are spread over.
    #[arg(long, default_value_t = 4)]
    pub connections: usize,
    /// Instead of the other measurements: the default job at each of --sizes with each of
    /// these light counts (comma-separated, 3..=256), each run in a process of its own.
    #[arg(long, value_delimiter = ',')]
    pub light_sweep: Vec<usize>,
    /// With --light-sweep: also run every job with this `photostereo` binary, alternately
    /// with this one's (e.g. a build of the previous version).
    #[arg(long)]
    pub against: Option<PathBuf>,
    /// With --light-sweep: options given to every job, of both binaries (e.g.
    /// `--integration weighted-poisson`, so that a binary with other defaults does the
    /// same work), as one space-separated value.
    #[arg(long, allow_hyphen_values = true, value_delimiter = ' ')]
    pub sweep_options: Vec<String>,
    /// With --light-sweep: the scene rendered. `sphere`: the matte textured sphere the
    /// other measurements use; `glossy`: `res/glossy`'s (a dark sphere under a GGX coat
    /// of roughness 0.2, highlights clipping a little), where the `glossy` solver fits a
    /// lobe at about a third of the object's pixels.
    #[arg(long, value_enum, default_value_t = SweepScene::Sphere)]
    pub sweep_scene: SweepScene,
    /// Instead of the other measurements: health and status probes, and the server's
    /// memory, under hostile loads, against `photostereo serve` run as a child process
    /// with its default limits (a fresh data directory per scenario).
    #[arg(long)]
    pub hostile: bool,
    /// With --hostile: the scenarios, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "quiet,idle,slowloris,slow-uploads,calibration-bomb,reshade-storm"
    )]
    pub scenarios: Vec<Scenario>,
    /// With --hostile: how long each load lasts, seconds (requests it sent are answered
    /// or given up within 120 s more).
    #[arg(long, default_value_t = 15)]
    pub hostile_seconds: u64,
    /// With --hostile: connections the idle and slowloris loads open.
    #[arg(long, default_value_t = 5000)]
    pub hostile_connections: usize,
    /// With --hostile: milliseconds between probes (a health and a status request, each
    /// on a new connection).
    #[arg(long, default_value_t = 100)]
    pub probe_ms: u64,
    /// With --hostile: more `serve` arguments, as one space-separated value (e.g.
    /// `--workers 1`).
    #[arg(long, allow_hyphen_values = true, value_delimiter = ' ')]
    pub serve_args: Vec<String>,
    /// Instead of the other measurements: the integrators alone on normal maps, at each of
    /// --sizes (a rendered perspective scene, against orthographic `robust-poisson`) and
    /// on --normal-maps.
    #[arg(long)]
    pub integrators: bool,
    /// With --integrators: a folder whose sub-folders each hold `normal_map.png`,
    /// `mask.png` and `K.txt` (e.g. ../shared/real/normals), integrated perspective.
    #[arg(long, requires = "integrators")]
    pub normal_maps: Option<PathBuf>,
    /// Instead of the other measurements: a chrome-ball calibration of 24 images of 27
    /// megapixels (`photostereo calibrate` in a child process), its time and peak memory.
    #[arg(long, conflicts_with_all = ["integrators", "hostile"])]
    pub calibration: bool,
    /// Instead of the other measurements: a near-light job (a ring of 24 LEDs over a
    /// relief plate) against the distant job on the same images, at each of --sizes
    /// (`photostereo reconstruct` in a child process), time and peak memory.
    #[arg(long, conflicts_with_all = ["integrators", "hostile", "calibration"])]
    pub near: bool,
    /// Where to create the temporary directory [default: the system's temp dir].
    #[arg(long)]
    pub tmp_dir: Option<PathBuf>,
}

impl BenchArgs {
    /// Refuse values the bench cannot measure with, naming the flag.
    pub(super) fn check(&self) -> anyhow::Result<()> {
        ensure!(!self.sizes.is_empty(), "--sizes needs at least one size");
        for &s in &self.sizes {
            ensure!(
                (32..=8192).contains(&s),
                "--sizes: {s} is outside 32..=8192"
            );
        }
        let mut seen = self.sizes.clone();
        seen.sort_unstable();
        seen.dedup();
        ensure!(
            seen.len() == self.sizes.len(),
            "--sizes: a size is repeated"
        );
        ensure!(
            (3..=64).contains(&self.lights),
            "--lights must be 3..=64 (the service takes at most 64 images)"
        );
        ensure!((1..=100).contains(&self.runs), "--runs must be 1..=100");
        for &n in &self.light_sweep {
            ensure!(
                (3..=256).contains(&n),
                "--light-sweep: {n} is outside 3..=256 (intake takes at most 256 images)"
            );
        }
        ensure!(
            self.sweep_scene == SweepScene::Sphere || !self.light_sweep.is_empty(),
            "--sweep-scene needs --light-sweep"
        );
        ensure!(
            (1..=100_000).contains(&self.requests),
            "--requests must be 1..=100000"
        );
        ensure!(
            (1..=64).contains(&self.connections),
            "--connections must be 1..=64"
        );
        ensure!(
            !self.scenarios.is_empty(),
            "--scenarios needs at least one scenario"
        );
        ensure!(
            (1..=600).contains(&self.hostile_seconds),
            "--hostile-seconds must be 1..=600"
        );
        ensure!(
            (1..=50_000).contains(&self.hostile_connections),
            "--hostile-connections must be 1..=50000"
        );
        ensure!(
            (10..=10_000).contains(&self.probe_ms),
            "--probe-ms must be 10..=10000"
        );
        Ok(())
    }
}

/// A hostile load of `bench --hostile`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Scenario {
    /// No load: the probes alone, for reference.
    Quiet,
    /// Connections that send nothing.
    Idle,
    /// Connections that trickle a request head, a byte a second, never ending it.
    Slowloris,
    /// Tenant A's 64 job uploads sent a byte at a time, while tenant B submits a job and
    /// a calibration.
    SlowUploads,
    /// A calibration of 24 all-black 5792 × 5792 PNGs.
    CalibrationBomb,
    /// 40 re-shades (`shaded.png?light=`) at once of a finished 2048² job.
    ReshadeStorm,
}

/// The scene `--light-sweep` renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SweepScene {
    Sphere,
    Glossy,
}

/// `bench`'s arguments from `args` (the flags after `bench`), checked: for tests.
#[cfg(test)]
pub(crate) fn parse(args: &[&str]) -> anyhow::Result<BenchArgs> {
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        bench: BenchArgs,
    }
    let cli = Cli::try_parse_from(std::iter::once("bench").chain(args.iter().copied()))?;
    cli.bench.check()?;
    Ok(cli.bench)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hostile_flags_parse_and_are_checked() {
        let all = parse(&["--hostile"]).unwrap();
        assert_eq!(all.scenarios.len(), 6);
        assert_eq!((all.hostile_seconds, all.hostile_connections), (15, 5000));
        let some = parse(&[
            "--hostile",
            "--scenarios",
            "idle,reshade-storm",
            "--serve-args",
            "--workers 1",
        ])
        .unwrap();
        assert_eq!(some.scenarios, [Scenario::Idle, Scenario::ReshadeStorm]);
        assert_eq!(some.serve_args, ["--workers", "1"]);
        assert!(parse(&["--hostile", "--scenarios", "flood"]).is_err());
        assert!(parse(&["--hostile", "--hostile-seconds", "0"]).is_err());
        assert!(parse(&["--hostile", "--probe-ms", "5"]).is_err());
        assert!(parse(&["--hostile", "--hostile-connections", "0"]).is_err());
    }

    #[test]
    fn the_sweep_scene_goes_with_a_light_sweep() {
        let sweep = parse(&["--light-sweep", "24", "--sweep-scene", "glossy"]).unwrap();
        assert_eq!(sweep.sweep_scene, SweepScene::Glossy);
        assert_eq!(parse(&[]).unwrap().sweep_scene, SweepScene::Sphere);
        let alone = parse(&["--sweep-scene", "glossy"]).unwrap_err();
        assert!(alone.to_string().contains("--light-sweep"), "{alone}");
        assert!(parse(&["--light-sweep", "24", "--sweep-scene", "bunny"]).is_err());
    }
}
