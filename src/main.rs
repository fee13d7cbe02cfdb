//! The `photostereo` binary: reconstruct a folder, render the project's data sets, or
//! serve the HTTP API.

mod bench;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use photostereo::core::bands::Stack;
use photostereo::core::intake::{self, DirMask, Limits};
use photostereo::core::normalmap::{Convention, Lens};
use photostereo::core::options::{Integration, Intensities, MaskMode, MeshNormals, Solver};
use photostereo::core::{Options, metrics, near, pipeline, stream, synth};
use photostereo::service;
use serde::de::DeserializeOwned;

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

#[derive(Args)]
struct ReconstructArgs {
    /// Folder in the seed's layout (images + light_directions.csv or .json) or the
    /// benchmark layout (light_directions.txt with x right, y UP, z to the camera,
    /// filenames.txt, optional light_intensities.txt); image files the table does not
    /// name are ignored, and a mask.png in it is the mask (see --mask).
    dir: PathBuf,
    /// Where to write the outputs.
    #[arg(long, short)]
    out: PathBuf,
    /// Folder for the decoded images while the solve reads them by band (unlinked files,
    /// 2 bytes per pixel per 16-bit gray image, gone when the run ends). Default: the
    /// output folder, or its nearest existing parent. Not a tmpfs: that holds them in memory.
    #[arg(long)]
    scratch_dir: Option<PathBuf>,
    /// Options as a JSON file (the HTTP API's `options` part); flags below override it.
    #[arg(long)]
    options: Option<PathBuf>,
    /// robust (default) | l2 | weighted
    #[arg(long, value_parser = kebab::<Solver>)]
    solver: Option<Solver>,
    /// auto (default) | none | given. Unless a mode is chosen (here or in --options), a
    /// mask.png in the folder (or --mask-file) makes it `given`; choosing auto or none
    /// leaves a folder mask.png unused.
    #[arg(long, value_parser = kebab::<MaskMode>)]
    mask: Option<MaskMode>,
    /// A mask image (non-zero = object), instead of the folder's mask.png; used unless
    /// --mask none.
    #[arg(long)]
    mask_file: Option<PathBuf>,
    /// robust-poisson (default) | weighted-poisson | poisson | frankot-chellappa | path
    #[arg(long, value_parser = kebab::<Integration>)]
    integration: Option<Integration>,
    /// Light for shaded.png, as x,y,z (default 1,2,3).
    #[arg(long, value_parser = xyz, allow_hyphen_values = true)]
    light: Option<[f64; 3]>,
    /// table (default): the light table's intensities (1 where it gives none; an LED
    /// given by position without one is estimated) | estimate: every light's relative
    /// intensity from the object itself, written back as lights.json.
    #[arg(long, value_parser = kebab::<Intensities>)]
    intensities: Option<Intensities>,
    /// Also score the solver without ground truth (result.json's `holdout`): each quarter
    /// of the lights left out in turn, the rest solved, the left-out images predicted.
    /// Four more solves; needs at least 8 images.
    #[arg(long)]
    holdout_lights: bool,
    /// Write these artifacts (comma-separated names, e.g. albedo.png,mesh.glb, or `all`)
    /// instead of the default set (albedo, mask, normal, height, confidence and shaded
    /// PNGs, mesh.glb, result.json). Near lights write all of theirs by default: albedo,
    /// normal, mask and depth pictures, points.ply, mesh.glb, result.json.
    #[arg(long, value_delimiter = ',')]
    outputs: Option<Vec<String>>,
    #[command(flatten)]
    limit: PixelLimit,
    /// Largest light-matrix condition number accepted.
    #[arg(long)]
    max_condition: Option<f64>,
    /// Mesh: upper bound on vertices.
    #[arg(long)]
    mesh_max_vertices: Option<usize>,
    /// Mesh: take every n-th pixel as a vertex.
    #[arg(long)]
    mesh_step: Option<usize>,
    /// Mesh: multiply heights by this.
    #[arg(long)]
    height_scale: Option<f32>,
    /// Mesh: size of a pixel in metres (positions in pixels when absent).
    #[arg(long)]
    pixel_size: Option<f64>,
    /// Mesh: photometric | geometric vertex normals.
    #[arg(long, value_parser = kebab::<MeshNormals>)]
    mesh_normals: Option<MeshNormals>,
    #[command(flatten)]
    camera: CameraArgs,
}

/// A pinhole camera, making the surface depth along the optical axis (depth.png,
/// depth.exr, points.ply; the mesh unprojected through it).
#[derive(Args)]
struct CameraArgs {
    /// A pinhole camera: a K.txt (3 × 3) or camera.json file, or fx,fy,cx,cy in pixels.
    /// Without it or --focal-length, `reconstruct` uses the folder's own camera.json or
    /// K.txt, `integrate` no camera (a file beside the map is only noted); without any,
    /// orthographic heights in pixels.
    #[arg(long)]
    camera: Option<String>,
    /// A pinhole camera with this focal length in pixels and its principal point at the
    /// image centre.
    #[arg(long, conflicts_with = "camera")]
    focal_length: Option<f64>,
    /// With a camera: the working distance, the median depth over the mask (metric depth
    /// in its unit); without it depth is relative, median 1.
    #[arg(long, allow_hyphen_values = true)]
    distance: Option<f64>,
}

/// How large a picture is read: as the server's `--max-pixels`, which bounds each image
/// or normal map of a job.
#[derive(Args)]
struct PixelLimit {
    /// Most pixels (width × height) in one image or normal map: larger files are refused
    /// before they are decoded.
    #[arg(long, default_value_t = Limits::default().max_pixels_per_image)]
    max_pixels: u64,
}

impl PixelLimit {
    fn limits(&self) -> Limits {
        Limits {
            max_pixels_per_image: self.max_pixels,
            ..Limits::default()
        }
    }
}

impl CameraArgs {
    /// Where `--camera` / `--focal-length` say the camera comes from, if they are given.
    fn lens(&self) -> anyhow::Result<Option<Lens>> {
        use photostereo::core::camera::Pinhole;
        Ok(match (self.camera.as_deref(), self.focal_length) {
            // A file when one is there, else the four numbers.
            (Some(c), _) if Path::new(c).is_file() => {
                Some(Lens::Pinhole(Pinhole::read(Path::new(c))?))
            }
            (Some(c), _) => Some(Lens::Pinhole(Pinhole::parse(c).with_context(|| {
                format!("--camera {c:?} is neither a file nor fx,fy,cx,cy")
            })?)),
            (None, Some(f)) => Some(Lens::Centred { focal_px: f }),
            (None, None) => None,
        })
    }
}

#[derive(Args)]
struct IntegrateArgs {
    /// The normal map: PNG, 8- or 16-bit RGB(A), decoded as n = 2·v/max − 1; or OpenEXR,
    /// 32-bit float, the vector itself. Black, grey (zero-length) and NaN pixels are
    /// background; result.json counts each kind.
    map: PathBuf,
    /// Where to write the outputs.
    #[arg(long, short)]
    out: PathBuf,
    /// A mask image (non-zero = object), intersected with the map's usable pixels; it
    /// must have the map's size.
    #[arg(long)]
    mask: Option<PathBuf>,
    #[command(flatten)]
    camera: CameraArgs,
    /// How the map's green channel points: opengl (y up; also the project's normal.png and
    /// the benchmarks' x right, y up, z to the camera: aliases project, benchmark) or
    /// directx (y down).
    #[arg(long, value_enum, default_value_t)]
    normal_convention: Convention,
    /// robust-poisson (default) | bilateral | weighted-poisson | poisson |
    /// frankot-chellappa | path
    #[arg(long, value_parser = kebab::<Integration>)]
    integration: Option<Integration>,
    /// Write these artifacts (comma-separated names, or `all`) instead of all of them:
    /// mask.png, normal.png, height.png and height.exr (depth.png and depth.exr with a
    /// camera), points.ply, mesh.glb; result.json is always written.
    #[arg(long, value_delimiter = ',')]
    outputs: Option<Vec<String>>,
    #[command(flatten)]
    limit: PixelLimit,
}

fn integrate(args: IntegrateArgs) -> anyhow::Result<()> {
    use photostereo::core::normalmap;
    use photostereo::core::normals_in::{self, Settings};
    let start = std::time::Instant::now();
    let lens = args.camera.lens()?;
    let mut settings = Settings {
        integration: args.integration.unwrap_or_default(),
        distance: args.camera.distance,
        outputs: args.outputs.clone(),
        ..Settings::default()
    };
    // Before the map is read: a misspelt name should not wait for a large map's decode.
    if let Some(names) = &settings.outputs {
        normals_in::check_outputs(names, lens.is_some())?;
    }
    if lens.is_none()
        && let Some(note) = normals_in::unused_camera_note(&args.map)
    {
        eprintln!("note: {note}");
        settings.notes.push(note);
    }
    let map = normalmap::read(
        &args.map,
        args.mask.as_deref(),
        args.normal_convention,
        lens,
        &args.limit.limits(),
    )?;
    settings.check(map.camera.as_ref())?;
    let c = map.counts;
    eprintln!(
        "{}×{} {}-bit normal map: {} pixels used ({} back-facing, {} renormalised); off the mask: {} black, {} zero-length, {} NaN/infinite, {} transparent, {} outside the mask",
        map.width,
        map.height,
        map.bits,
        c.used,
        c.back_facing,
        c.not_unit,
        c.black,
        c.zero_length,
        c.non_finite,
        c.transparent,
        c.outside_mask
    );
    let report = normals_in::run(map, &settings, &args.out, &mut photostereo::core::RunToEnd)?;
    let (what, range) = match report.output {
        "depth" => ("depth", (report.depth_min, report.depth_max)),
        _ => ("heights (px)", (report.height_min, report.height_max)),
    };
    eprintln!(
        "{what} {:.4}..{:.4}, total {:.0} ms",
        range.0.unwrap_or(f32::NAN),
        range.1.unwrap_or(f32::NAN),
        start.elapsed().as_secs_f64() * 1e3
    );
    println!("{}", args.out.display());
    Ok(())
}

#[derive(Args)]
struct CalibrateArgs {
    /// Folder of chrome sphere images, one per light. A light_directions.csv (or .json) or
    /// names.txt in it gives the light table's names, one per image in the same order
    /// (only the names are read); without one, rows are named by the image files.
    dir: PathBuf,
    /// Where to write the light table (`name, x, y, z[, intensity]`; x = column right,
    /// y = row down, z towards the camera); a name ending in `.lp` writes the `.lp` file
    /// of RTIBuilder and RelightLab instead (count, then `name x y z`, y up).
    #[arg(long, short)]
    out: PathBuf,
    /// The sphere's circle in pixels, as cx,cy,r (0-based, pixel centres at integers: the
    /// first pixel's centre is 0,0) instead of fitting its outline. Give it once per ball
    /// when the frame holds several: each is calibrated and the lights are placed where
    /// the balls' rays meet (--positions). Without it every ball in the frame is found
    /// (round outlines of one size side by side, each showing the lights' highlights),
    /// the first ball being the leftmost.
    #[arg(long, value_parser = circle_arg, allow_hyphen_values = true)]
    circle: Vec<[f64; 3]>,
    /// With two balls or more (each given by --circle, or found when none is given):
    /// write the lights' positions (`name, x, y, z`) here; an error when one ball is
    /// given or found.
    #[arg(long)]
    positions: Option<PathBuf>,
    /// The balls' diameter, in the unit the positions should be in (default: ball radii).
    #[arg(long)]
    ball_diameter: Option<f64>,
    /// A mask image of the sphere (non-zero = sphere) instead of fitting its outline.
    #[arg(long)]
    sphere_mask: Option<PathBuf>,
    /// Write the overlay picture (circle and numbered highlights over the maximum image).
    #[arg(long)]
    overlay: Option<PathBuf>,
    /// Write the diagram of the light directions on the unit hemisphere.
    #[arg(long)]
    lights_png: Option<PathBuf>,
    /// A perspective camera with this focal length in pixels (principal point at the image
    /// centre); orthographic without it.
    #[arg(long)]
    focal_length: Option<f64>,
    /// Folder of matte white sphere images under the same lights (same order): fits each
    /// light's relative intensity, written as the table's fifth column.
    #[arg(long)]
    matte: Option<PathBuf>,
    /// Leave out images without a usable highlight (reported) instead of failing.
    #[arg(long)]
    skip_bad: bool,
}

fn calibrate(args: CalibrateArgs) -> anyhow::Result<()> {
    use photostereo::core::calibrate::{self, Camera, Circle, CircleSource, Settings, Source};
    let folder = calibrate::load_dir(&args.dir)?;
    let (images, names) = (&folder.images, &folder.names);
    let circles: Vec<Circle> = args
        .circle
        .iter()
        .map(|&[cx, cy, r]| Circle { cx, cy, r })
        .collect();
    let circle = match (circles.len(), &args.sphere_mask) {
        (1.., Some(_)) => anyhow::bail!("give --circle or --sphere-mask, not both"),
        (1, None) => CircleSource::Given(circles[0]),
        (2.., None) => CircleSource::Balls(circles),
        (0, Some(mask)) => calibrate::read_mask(mask)?,
        (0, None) => CircleSource::Fit,
    };
    if let Some(d) = args.ball_diameter
        && !(d.is_finite() && d > 0.0)
    {
        anyhow::bail!("--ball-diameter must be a positive number, got {d}");
    }
    if args.positions.is_some() && (args.circle.len() == 1 || args.sphere_mask.is_some()) {
        anyhow::bail!(
            "--positions needs two balls or more in the frame: give each by --circle cx,cy,r, or none to have them found"
        );
    }
    let camera = match args.focal_length {
        Some(f) if calibrate::FOCAL_PX.contains(&f) => {
            let (w, h) = if images.count() > 0 {
                images.size(0)?
            } else {
                (1, 1)
            };
            Camera::Perspective {
                focal_px: f,
                principal: [(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0],
            }
        }
        Some(f) => anyhow::bail!(
            "--focal-length must be a number of pixels from {} to {:e} (leave it out for a long lens far away), got {f}",
            calibrate::FOCAL_PX.start(),
            calibrate::FOCAL_PX.end()
        ),
        None => Camera::Orthographic,
    };
    let settings = Settings {
        circle,
        camera,
        skip_bad: args.skip_bad,
        budget: Default::default(),
        scratch: None,
    };
    if let Some(a) = folder.ambient_source() {
        eprintln!("ambient image: {}", a.name(0));
    }
    let mut cal =
        calibrate::calibrate(images, names.as_deref(), folder.ambient_source(), &settings)?;
    if let Some(matte) = &args.matte {
        cal.fit_intensities(&calibrate::load_images(matte)?, &settings)?;
    }
    if args.positions.is_some() && cal.more_circles.is_empty() {
        let c = cal.circle;
        anyhow::bail!(
            "--positions needs two balls or more in the frame, but one ball was found (centre ({:.1}, {:.1}), radius {:.1} px): give each ball by --circle cx,cy,r",
            c.cx,
            c.cy,
            c.r
        );
    }
    print_balls(&cal);
    eprint!("{}", cal.quality_table());
    for s in &cal.skipped {
        eprintln!("skipped {}: {}", s.image, s.reason);
    }
    let write = |path: &PathBuf, bytes: &[u8]| {
        std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
    };
    for l in &cal.lights {
        if let Some(p) = &l.position {
            let k = args.ball_diameter.map_or(1.0, |d| d / 2.0);
            eprintln!(
                "position {:>3}  {:<20}  {:>9.3}, {:>9.3}, {:>9.3}  residual {:.3}  rays {:.2}° apart",
                l.index + 1,
                l.name,
                k * p.position[0],
                k * p.position[1],
                k * p.position[2],
                k * p.residual,
                p.spread_deg
            );
        }
    }
    let is_lp = args
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("lp"));
    if is_lp && cal.lights.iter().any(|l| l.intensity.is_some()) {
        eprintln!(
            "note: a .lp table has no intensity column; the matte sphere's intensities are left out"
        );
    }
    let table = if is_lp { cal.lp_table() } else { cal.table() };
    write(&args.out, table.as_bytes())?;
    if let (Some(path), Some(table)) = (&args.positions, cal.positions_table(args.ball_diameter)) {
        write(path, table.as_bytes())?;
    }
    if let Some(p) = &args.overlay {
        write(p, &cal.overlay_png())?;
    }
    if let Some(p) = &args.lights_png {
        write(p, &cal.lights_png())?;
    }
    println!("{}", args.out.display());
    Ok(())
}

/// The balls' circles as the calibration used them (`sphere` with one ball, `sphere 1`,
/// `sphere 2`… with several, the first being the positions' origin), and the round
/// outlines found that were no balls.
fn print_balls(cal: &photostereo::core::calibrate::Calibration) {
    let several = !cal.more_circles.is_empty();
    let circles = std::iter::once(&cal.circle).chain(&cal.more_circles);
    for (k, c) in circles.enumerate() {
        let fit = match k {
            0 => cal.outline.as_ref(),
            k => cal.more_outlines.get(k - 1),
        };
        let label = match several {
            true => format!("sphere {}", k + 1),
            false => "sphere".to_string(),
        };
        let how = match fit {
            Some(fit) => format!(
                "outline fitted along {:.0} % of the circle, RMS {:.2} px",
                100.0 * fit.coverage,
                fit.rms
            ),
            None => "given".to_string(),
        };
        eprintln!(
            "{label}: centre ({:.2}, {:.2}), radius {:.2} px ({how})",
            c.cx, c.cy, c.r
        );
    }
    for c in &cal.not_balls {
        eprintln!(
            "left out the round outline at ({:.1}, {:.1}), radius {:.1} px: it shows no highlight in most images, so it is no ball",
            c.cx, c.cy, c.r
        );
    }
}

/// Parse a flag value by the same kebab-case names the JSON options use.
fn kebab<T: DeserializeOwned>(s: &str) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string())).map_err(|e| e.to_string())
}

/// `x,y,z`: three numbers separated by commas.
fn xyz(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts[..] else {
        return Err(format!("expected x,y,z (three numbers), got {s:?}"));
    };
    let num = |v: &str| v.parse::<f64>().map_err(|e| format!("{v:?}: {e}"));
    Ok([num(x)?, num(y)?, num(z)?])
}

/// `cx,cy,r`: a circle in pixels.
fn circle_arg(s: &str) -> Result<[f64; 3], String> {
    xyz(s).map_err(|_| format!("expected cx,cy,r (three numbers, pixels), got {s:?}"))
}

impl ReconstructArgs {
    /// The options, the mask mode if the user chose one (by flag or in the file), and the
    /// fields the options file names.
    fn options(&self) -> anyhow::Result<(Options, Option<MaskMode>, Vec<String>)> {
        let (mut o, mut chosen, fields): (Options, _, Vec<String>) = match &self.options {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("reading {}", p.display()))?;
                let o: Options = serde_json::from_str(&text)
                    .with_context(|| format!("options in {}", p.display()))?;
                let fields: Vec<String> = serde_json::from_str::<serde_json::Value>(&text)
                    .ok()
                    .and_then(|v| Some(v.as_object()?.keys().cloned().collect()))
                    .unwrap_or_default();
                let chosen = fields.iter().any(|f| f == "mask").then_some(o.mask);
                (o, chosen, fields)
            }
            None => (Options::default(), None, Vec::new()),
        };
        chosen = self.mask.or(chosen);
        macro_rules! set {
            ($($flag:ident => $($field:ident).+),*) => { $(if let Some(v) = self.$flag.clone() { o.$($field).+ = v; })* };
        }
        set!(solver => solver, mask => mask, integration => integration, max_condition => max_condition, intensities => intensities,
             height_scale => mesh.height_scale, mesh_max_vertices => mesh.max_vertices, mesh_normals => mesh.normals);
        if let Some(l) = self.light {
            o.shading_light = l;
        }
        if self.outputs.is_some() {
            o.outputs = self.outputs.clone();
        }
        o.holdout_lights |= self.holdout_lights;
        if self.mesh_step.is_some() {
            o.mesh.step = self.mesh_step;
        }
        if self.pixel_size.is_some() {
            o.mesh.pixel_size = self.pixel_size;
        }
        if self.camera.distance.is_some() {
            o.distance = self.camera.distance;
        }
        o.check_values()?;
        Ok((o, chosen, fields))
    }

    /// Refuses what a near-light reconstruction would leave unused: the distant solve's
    /// flags (`--solver`, `--light`, `--max-condition`), fields of the options file other
    /// than [`near::OPTIONS`], and outputs it never writes ([`near::check_outputs`]).
    fn check_near(&self, file_fields: &[String], opts: &Options) -> anyhow::Result<()> {
        let distant = [
            ("--solver", self.solver.is_some()),
            ("--light", self.light.is_some()),
            ("--max-condition", self.max_condition.is_some()),
            ("--holdout-lights", self.holdout_lights),
        ];
        if let Some((flag, _)) = distant.iter().find(|(_, given)| *given) {
            anyhow::bail!(
                "{flag} does not apply to near lights (the light table gives positions); a near-light reconstruction takes --mask, --mask-file, --integration, --intensities, --outputs, the mesh flags, --camera, --focal-length and --distance"
            );
        }
        let other = file_fields
            .iter()
            .find(|f| !near::OPTIONS.contains(&f.as_str()));
        if let (Some(file), Some(field)) = (&self.options, other) {
            anyhow::bail!(
                "field `{field}` of {} does not apply to near lights (the light table gives positions), which take {}",
                file.display(),
                near::OPTIONS.join(", ")
            );
        }
        if let Some(names) = &opts.outputs {
            near::check_outputs(names).with_context(|| match &self.options {
                Some(file) if self.outputs.is_none() => format!("outputs in {}", file.display()),
                _ => "--outputs".to_string(),
            })?;
        }
        Ok(())
    }

    /// Which mask the folder's set gets: --mask-file, else the folder's mask.png unless
    /// the user chose a mode that takes none of its own accord (auto or none).
    fn scratch_dir(&self) -> PathBuf {
        if let Some(dir) = &self.scratch_dir {
            return dir.clone();
        }
        let beside = self.out.ancestors().find(|a| a.is_dir());
        beside.map_or_else(|| PathBuf::from("."), Path::to_path_buf)
    }

    /// The camera of a `width × height` set: `flags` (--camera or --focal-length), else the
    /// options file's, else the folder's own camera.json or K.txt. Returns the notes for
    /// `result.json`: which file was used, or left unused.
    fn resolve_camera(
        &self,
        flags: Option<Lens>,
        opts: &mut Options,
        (width, height): (usize, usize),
    ) -> anyhow::Result<Vec<String>> {
        use photostereo::core::camera::Pinhole;
        if let Some(lens) = flags {
            opts.camera = Some(lens.resolve(width, height));
        }
        let Some(file) = Pinhole::file_in(&self.dir) else {
            return Ok(Vec::new());
        };
        let note = if opts.camera.is_some() {
            format!("{} not used: a camera was given", file.display())
        } else {
            opts.camera = Some(Pinhole::read(&file)?);
            format!("camera from {}", file.display())
        };
        Ok(vec![note])
    }

    fn dir_mask(&self, chosen: Option<MaskMode>) -> DirMask<'_> {
        match (&self.mask_file, chosen) {
            (Some(file), _) => DirMask::File(file),
            (None, None | Some(MaskMode::Given)) => DirMask::Folder,
            (None, Some(MaskMode::Auto | MaskMode::None)) => DirMask::Without,
        }
    }
}

fn reconstruct(args: ReconstructArgs) -> anyhow::Result<()> {
    let (mut opts, chosen, file_fields) = args.options()?;
    let flags = args.camera.lens()?;
    let table = intake::dir_table(&args.dir)?;
    if table.lights.iter().any(|l| l.emitter.is_some()) {
        args.check_near(&file_fields, &opts)?;
        return reconstruct_near(&args, opts, chosen, flags, table.rig);
    }
    let start = std::time::Instant::now();
    let scratch = args.scratch_dir();
    let set = stream::open_dir(
        &args.dir,
        args.dir_mask(chosen),
        &args.limit.limits(),
        &scratch,
    )?;
    // A folder's own mask.png stands for `--mask given` unless a mode was chosen.
    if chosen.is_none() && set.info().mask.is_some() && args.mask_file.is_none() {
        opts.mask = MaskMode::Given;
    }
    let mut notes = set.info().notes.clone();
    let size = (set.info().width, set.info().height);
    notes.extend(args.resolve_camera(flags, &mut opts, size)?);
    for note in &notes {
        eprintln!("note: {note}");
    }
    let set = set.noted(notes);
    let decoded = start.elapsed();
    let report = pipeline::run(
        set,
        &opts,
        &args.out,
        &mut |stage: photostereo::core::progress::Stage| {
            eprintln!("  {}", stage.as_str());
            true
        },
    )?;
    let (low, high) = report.surface_range();
    let surface = match report.options.camera {
        None => format!("heights {low:.2}..{high:.2} px"),
        Some(_) => format!("depth {low:.4}..{high:.4}"),
    };
    eprintln!(
        "{}×{} from {} images: decode {:.0} ms, total {:.0} ms; {surface}, reprojection RMS {:.4}, integrability RMS {:.4}",
        report.width,
        report.height,
        report.light_count,
        decoded.as_secs_f64() * 1e3,
        start.elapsed().as_secs_f64() * 1e3,
        report.reprojection_rms,
        report.integrability_rms
    );
    println!("{}", args.out.display());
    Ok(())
}

/// A folder whose light table gives positions: the near-light solve, the set read in
/// bands as `reconstruct` reads it. The camera is the flags', the options file's, the
/// table's or the folder's (K.txt, camera.json); the working distance `--distance`, the
/// options file's or the table's.
fn reconstruct_near(
    args: &ReconstructArgs,
    mut opts: Options,
    chosen: Option<MaskMode>,
    flags: Option<Lens>,
    rig: photostereo::core::lights::Rig,
) -> anyhow::Result<()> {
    let start = std::time::Instant::now();
    let scratch = args.scratch_dir();
    let limits = args.limit.limits();
    let mut set = stream::open_dir(&args.dir, args.dir_mask(chosen), &limits, &scratch)?;
    if chosen.is_none() && set.info().mask.is_some() && args.mask_file.is_none() {
        opts.mask = MaskMode::Given;
    }
    let (width, height) = (set.info().width, set.info().height);
    let folder_camera = photostereo::core::camera::Pinhole::file_in(&args.dir);
    let camera = match (flags, opts.camera.or(rig.camera), folder_camera) {
        (Some(lens), ..) => lens.resolve(width, height),
        (None, Some(c), _) => c,
        (None, None, Some(file)) => photostereo::core::camera::Pinhole::read(&file)?,
        (None, None, None) => anyhow::bail!(
            "the light table gives positions but no camera: add \"camera\" to it, put a \
             K.txt or camera.json in the folder, or give --camera"
        ),
    };
    camera.check(width, height)?;
    let Some(distance) = opts.distance.or(rig.distance) else {
        anyhow::bail!(
            "near lights need the working distance to the object: add \"distance\" to the light table or give --distance"
        );
    };
    for note in &set.info().notes {
        eprintln!("note: {note}");
    }
    let report = near::run(
        &mut set,
        camera,
        distance,
        rig.unit,
        &opts,
        &args.out,
        &mut |stage: photostereo::core::progress::Stage| {
            eprintln!("  {}", stage.as_str());
            true
        },
    )?;
    let unit = report.unit.as_deref().unwrap_or("");
    eprintln!(
        "{}×{} from {} near lights: {} iterations{}, median depth {:.4} {unit} ({:.4}..{:.4}), total {:.0} ms",
        report.width,
        report.height,
        report.light_count,
        report.iterations.len(),
        if report.converged {
            ""
        } else {
            " (not settled)"
        },
        report.median_depth,
        report.depth_min,
        report.depth_max,
        start.elapsed().as_secs_f64() * 1e3,
    );
    println!("{}", args.out.display());
    Ok(())
}

fn render(dir: PathBuf, only: Vec<String>) -> anyhow::Result<()> {
    for (name, scene, lights, capture) in synth::catalogue() {
        if !only.is_empty() && !only.iter().any(|o| o == name) {
            continue;
        }
        let out = dir.join(name);
        synth::write_set(&out, &scene, &lights, &capture)?;
        println!("{}", out.display());
    }
    for (name, set) in synth::chrome_catalogue() {
        if !only.is_empty() && !only.iter().any(|o| o == name) {
            continue;
        }
        let out = dir.join(name);
        set.write(&out, None)?;
        println!("{}", out.display());
    }
    Ok(())
}

fn evaluate(dir: PathBuf, integration: Integration) -> anyhow::Result<()> {
    use photostereo::core::camera::Pinhole;
    use photostereo::core::metrics::Align;
    let mut sets: Vec<PathBuf> = std::fs::read_dir(&dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("truth").is_dir())
        .collect();
    sets.sort();
    println!(
        "| scene | solver | mean ° | median ° | depth MAE | depth RMS | depth in | solve ms |"
    );
    println!("|---|---|---:|---:|---:|---:|---|---:|");
    for set_dir in sets {
        let truth = synth::read_truth(&set_dir)?;
        let mut set = intake::load_dir(&set_dir, DirMask::Folder, &Limits::default())?;
        set.mask = Some(truth.mask.clone());
        // A set with a camera is perspective: its truth is depth along the optical axis.
        let camera = Pinhole::in_folder(&set_dir)?;
        let (align, unit) = match camera {
            None => (Align::Offset, "px, offset"),
            Some(_) => (Align::Scale, "truth's unit, scaled"),
        };
        for solver in [Solver::L2, Solver::Weighted, Solver::Robust, Solver::Glossy] {
            let opts = Options {
                solver,
                integration,
                camera,
                ..Options::default()
            };
            let rec = pipeline::reconstruct(&set, &opts, &mut photostereo::core::RunToEnd)?;
            let acc = metrics::accuracy(&rec, &truth, &truth.mask);
            let depth = metrics::depth_error(&rec.heights, &truth.depth, &truth.mask, align);
            let solve_ms = rec
                .report
                .timings_ms
                .iter()
                .find(|t| t.stage == "solve")
                .map_or(0.0, |t| t.ms);
            println!(
                "| {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {unit} | {:.0} |",
                set_dir.file_name().unwrap_or_default().to_string_lossy(),
                serde_json::to_value(solver)?.as_str().unwrap_or_default(),
                acc.mean_deg,
                acc.median_deg,
                depth.mean_abs,
                depth.rms,
                solve_ms
            );
        }
    }
    println!(
        "\nDepth: heights aligned by the median of (true − estimated), in pixels; under a \
         camera (a set with camera.json or K.txt), depth scaled by the median of \
         (true / estimated), in the truth's unit, MAE being the field's MADE."
    );
    Ok(())
}

/// `evaluate --holdout-lights`: each solver's prediction of left-out images of one capture.
fn evaluate_holdout(dir: PathBuf) -> anyhow::Result<()> {
    use photostereo::core::bands::InMemory;
    use photostereo::core::holdout;
    let set = intake::load_dir(&dir, DirMask::Folder, &Limits::default())?;
    anyhow::ensure!(
        set.lights.len() >= holdout::MIN_IMAGES,
        "--holdout-lights needs at least {} images (each quarter of the lights is left \
         out in turn); {} has {}",
        holdout::MIN_IMAGES,
        dir.display(),
        set.lights.len()
    );
    println!("| solver | median relative error | mean | as the table says | observations |");
    println!("|---|---:|---:|---:|---:|");
    for solver in [Solver::L2, Solver::Robust, Solver::Glossy] {
        let opts = Options {
            solver,
            ..Options::default()
        };
        let score = holdout::holdout(&mut InMemory::new(&set), &opts, &|| false)?;
        println!(
            "| {} | {:.4} | {:.4} | {:.4} | {} |",
            serde_json::to_value(solver)?.as_str().unwrap_or_default(),
            score.median_relative,
            score.mean_relative,
            score.median_relative_table,
            score.observations
        );
    }
    println!(
        "\nEach quarter of the lights (every 4th) left out in turn; the rest reconstructed \
         (auto mask); left-out object pixels neither clipped nor darker than 2 % scored, \
         relative error, each left-out light's intensity fitted (one scale per image; \
         \"as the table says\": the median with the table's intensities)."
    );
    Ok(())
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
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
