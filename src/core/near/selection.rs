//! What a near-light run takes and writes: the job options it reads ([`OPTIONS`]) and the
//! artifacts an `outputs` selection may name ([`ARTIFACTS`]), so that the CLI and the
//! service refuse the rest instead of leaving it unused.

use crate::core::error::InputError;
use crate::core::outputs;

/// The job options (`Options` fields) a near-light run reads: the mask mode, the
/// integration, the mesh, the outputs, the camera and working distance (which otherwise
/// come from the light table), and where the intensities come from. The solver, shading
/// light and condition bound are the distant reconstruction's.
pub const OPTIONS: [&str; 7] = [
    "mask",
    "integration",
    "mesh",
    "outputs",
    "camera",
    "distance",
    "intensities",
];

/// Every artifact a near-light run can be asked for, in the order it writes them: the
/// pictures, the geometry, `result.json` (always written). `lights.json`, the table with
/// the intensities it estimated, is written whenever it estimates them and is not
/// selected ([`outputs::UNSELECTED`]).
pub const ARTIFACTS: [&str; 8] = [
    "albedo.png",
    "normal.png",
    "mask.png",
    "depth.exr",
    "depth.png",
    "points.ply",
    "mesh.glb",
    "result.json",
];

/// The pictures of [`ARTIFACTS`] (PNG and EXR), which `outputs::write_pictures` encodes.
pub fn pictures() -> impl Iterator<Item = &'static str> {
    ARTIFACTS
        .into_iter()
        .filter(|n| n.ends_with(".png") || n.ends_with(".exr"))
}

/// Refuses an `outputs` selection that names what a near-light run never writes (the
/// heights and the distant reconstruction's other maps), or `lights.json`, which no
/// selection chooses.
pub fn check_outputs(names: &[String]) -> Result<(), InputError> {
    outputs::check_selection(names)?;
    let refuse = |why: String| Err(InputError::Options(format!("field `outputs`: {why}")));
    for name in names.iter().map(String::as_str) {
        if name == outputs::ALL || ARTIFACTS.contains(&name) {
            continue;
        }
        if outputs::UNSELECTED.contains(&name) {
            return refuse(format!(
                "{name:?} is not chosen by a selection: a near-light run writes it whenever it estimates the lights' intensities; it writes {}, or {:?} for all of them",
                ARTIFACTS.join(", "),
                outputs::ALL
            ));
        }
        return refuse(format!(
            "a near-light run writes no {name:?}; it writes {}, or {:?} for all of them",
            ARTIFACTS.join(", "),
            outputs::ALL
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: &[&str]) -> Vec<String> {
        n.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn outputs_a_near_run_cannot_write_are_refused_naming_what_it_writes() {
        assert!(check_outputs(&[]).is_ok());
        assert!(check_outputs(&names(&["all"])).is_ok());
        assert!(check_outputs(&names(&ARTIFACTS)).is_ok());
        assert!(check_outputs(&names(&["depth.exr", "points.ply", "all"])).is_ok());
        let refused = |n: &[&str]| match check_outputs(&names(n)) {
            Err(InputError::Options(m)) => m,
            other => panic!("{n:?}: {other:?}"),
        };
        let writes = "albedo.png, normal.png, mask.png, depth.exr, depth.png, points.ply, mesh.glb, result.json";
        for name in ["height.png", "height.exr", "shaded.png", "albedo_rgb.png"] {
            let e = refused(&["depth.exr", name]);
            assert!(e.starts_with("field `outputs`: "), "{e}");
            assert!(e.contains(&format!("{name:?}")), "{e}");
            assert!(e.contains(writes) && e.contains("\"all\""), "{e}");
        }
        let e = refused(&["lights.json"]);
        assert!(
            e.starts_with("field `outputs`: ") && e.contains("\"lights.json\""),
            "{e}"
        );
        assert!(e.contains("estimates the lights' intensities"), "{e}");
        // A name no run writes is the selection's own refusal.
        let e = refused(&["everything"]);
        assert!(e.contains("unknown output \"everything\""), "{e}");
    }

    #[test]
    fn the_pictures_are_the_artifacts_write_pictures_encodes() {
        let pictures: Vec<&str> = pictures().collect();
        assert_eq!(
            pictures,
            [
                "albedo.png",
                "normal.png",
                "mask.png",
                "depth.exr",
                "depth.png"
            ]
        );
        assert!(ARTIFACTS.iter().all(|n| outputs::content_type(n).is_some()));
    }
}
