//! `photostereo reconstruct`: a folder's images and lights into maps, heights and
//! meshes, through the distant-light pipeline or, for a table of LED positions, the
//! near-light one.

use std::path::{Path, PathBuf};

use super::flags::{CameraArgs, PixelLimit, kebab, xyz};
use anyhow::Context;
use clap::Args;
use photostereo::core::bands::Stack;
use photostereo::core::intake::{self, DirMask};
use photostereo::core::normalmap::Lens;
use photostereo::core::options::{Integration, Intensities, MaskMode, MeshNormals, Solver};
use photostereo::core::{Options, near, pipeline, stream};

#[derive(Args)]
pub(crate) struct ReconstructArgs {
    /// Folder in the seed's layout (images + light_directions.csv or .json) or the
    /// benchmark layout (light_directions.txt with x right, y UP, z to the camera,
    /// filenames.txt, optional light_intensities.txt); image files the table does not
    /// name are ignored, and a mask.png in it is the mask (see --mask).
    pub(crate) dir: PathBuf,
    /// Where to write the outputs.
    #[arg(long, short)]
    pub(crate) out: PathBuf,
    /// Folder for the decoded images while the solve reads them by band (unlinked files,
    /// 2 bytes per pixel per 16-bit gray image, gone when the run ends). Default: the
    /// output folder, or its nearest existing parent. Not a tmpfs: that holds them in memory.
    #[arg(long)]
    pub(crate) scratch_dir: Option<PathBuf>,
    /// Options as a JSON file (the HTTP API's `options` part); flags below override it.
    #[arg(long)]
    pub(crate) options: Option<PathBuf>,
    /// robust (default) | l2 | weighted | glossy (a lobe fitted where a pixel shows highlights)
    #[arg(long, value_parser = kebab::<Solver>)]
    pub(crate) solver: Option<Solver>,
    /// auto (default) | none | given. Unless a mode is chosen (here or in --options), a
    /// mask.png in the folder (or --mask-file) makes it `given`; choosing auto or none
    /// leaves a folder mask.png unused.
    #[arg(long, value_parser = kebab::<MaskMode>)]
    pub(crate) mask: Option<MaskMode>,
    /// A mask image (non-zero = object), instead of the folder's mask.png; used unless
    /// --mask none.
    #[arg(long)]
    pub(crate) mask_file: Option<PathBuf>,
    /// robust-poisson (default) | weighted-poisson | poisson | frankot-chellappa | path
    #[arg(long, value_parser = kebab::<Integration>)]
    pub(crate) integration: Option<Integration>,
    /// Light for shaded.png, as x,y,z (default 1,2,3).
    #[arg(long, value_parser = xyz, allow_hyphen_values = true)]
    pub(crate) light: Option<[f64; 3]>,
    /// table (default): the light table's intensities (1 where it gives none; an LED
    /// given by position without one is estimated) | estimate: every light's relative
    /// intensity from the object itself, written back as lights.json.
    #[arg(long, value_parser = kebab::<Intensities>)]
    pub(crate) intensities: Option<Intensities>,
    /// Also score the solver without ground truth (result.json's `holdout`): each quarter
    /// of the lights left out in turn, the rest solved, the left-out images predicted.
    /// Four more solves; needs at least 8 images.
    #[arg(long)]
    pub(crate) holdout_lights: bool,
    /// Write these artifacts (comma-separated names, e.g. albedo.png,mesh.glb, or `all`)
    /// instead of the default set (albedo, mask, normal, height, confidence and shaded
    /// PNGs, mesh.glb, result.json). Near lights write all of theirs by default: albedo,
    /// normal, mask and depth pictures, points.ply, mesh.glb, result.json.
    #[arg(long, value_delimiter = ',')]
    pub(crate) outputs: Option<Vec<String>>,
    #[command(flatten)]
    pub(crate) limit: PixelLimit,
    /// Largest light-matrix condition number accepted.
    #[arg(long)]
    pub(crate) max_condition: Option<f64>,
    /// Mesh: upper bound on vertices.
    #[arg(long)]
    pub(crate) mesh_max_vertices: Option<usize>,
    /// Mesh: take every n-th pixel as a vertex.
    #[arg(long)]
    pub(crate) mesh_step: Option<usize>,
    /// Mesh: multiply heights by this.
    #[arg(long)]
    pub(crate) height_scale: Option<f32>,
    /// Mesh: size of a pixel in metres (positions in pixels when absent).
    #[arg(long)]
    pub(crate) pixel_size: Option<f64>,
    /// Mesh: photometric | geometric vertex normals.
    #[arg(long, value_parser = kebab::<MeshNormals>)]
    pub(crate) mesh_normals: Option<MeshNormals>,
    #[command(flatten)]
    pub(crate) camera: CameraArgs,
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

pub(crate) fn reconstruct(args: ReconstructArgs) -> anyhow::Result<()> {
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
pub(crate) fn reconstruct_near(
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
