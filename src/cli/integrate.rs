//! `photostereo integrate`: a normal map from anywhere into heights or depth.

use std::path::PathBuf;

use super::flags::{CameraArgs, PixelLimit, kebab};
use clap::Args;
use photostereo::core::normalmap::Convention;
use photostereo::core::options::Integration;

#[derive(Args)]
pub(crate) struct IntegrateArgs {
    /// The normal map: PNG, 8- or 16-bit RGB(A), decoded as n = 2·v/max − 1; or OpenEXR,
    /// 32-bit float, the vector itself. Black, grey (zero-length) and NaN pixels are
    /// background; result.json counts each kind.
    pub(crate) map: PathBuf,
    /// Where to write the outputs.
    #[arg(long, short)]
    pub(crate) out: PathBuf,
    /// A mask image (non-zero = object), intersected with the map's usable pixels; it
    /// must have the map's size.
    #[arg(long)]
    pub(crate) mask: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) camera: CameraArgs,
    /// How the map's green channel points: opengl (y up; also the project's normal.png and
    /// the benchmarks' x right, y up, z to the camera: aliases project, benchmark) or
    /// directx (y down).
    #[arg(long, value_enum, default_value_t)]
    pub(crate) normal_convention: Convention,
    /// robust-poisson (default) | bilateral | weighted-poisson | poisson |
    /// frankot-chellappa | path
    #[arg(long, value_parser = kebab::<Integration>)]
    pub(crate) integration: Option<Integration>,
    /// Write these artifacts (comma-separated names, or `all`) instead of all of them:
    /// mask.png, normal.png, height.png and height.exr (depth.png and depth.exr with a
    /// camera), points.ply, mesh.glb; result.json is always written.
    #[arg(long, value_delimiter = ',')]
    pub(crate) outputs: Option<Vec<String>>,
    #[command(flatten)]
    pub(crate) limit: PixelLimit,
}

pub(crate) fn integrate(args: IntegrateArgs) -> anyhow::Result<()> {
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
