//! `.lp` light tables (RTIBuilder, RelightLab, the PTM and HSH fitters): a rendered set's
//! lights written as an `.lp` file in place of its CSV reconstruct to the same normals,
//! and the file's frame (y up) is the one the truth needs.

use std::path::Path;

use photostereo::core::intake::{self, DirMask, Limits};
use photostereo::core::lights::{self, lp};
use photostereo::core::synth::{self, Capture, Scene};
use photostereo::core::{Options, Reconstruction, RunToEnd, metrics, reconstruct};

fn run(dir: &Path) -> Reconstruction {
    let set = intake::load_dir(dir, DirMask::Folder, &Limits::default()).unwrap();
    reconstruct(&set, &Options::default(), &mut RunToEnd).unwrap()
}

/// The largest angle between two normal maps, degrees (atan2 of |a × b| and a · b, exact
/// for small angles where acos is not).
fn max_angle_deg(a: &Reconstruction, b: &Reconstruction) -> f64 {
    let (na, nb) = (&a.normals, &b.normals);
    assert_eq!(na.dim(), nb.dim());
    let (h, w, _) = na.dim();
    let mut worst = 0.0f64;
    for r in 0..h {
        for c in 0..w {
            let u = [0, 1, 2].map(|k| f64::from(na[[r, c, k]]));
            let v = [0, 1, 2].map(|k| f64::from(nb[[r, c, k]]));
            let cross = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let sin = cross.iter().map(|x| x * x).sum::<f64>().sqrt();
            let cos: f64 = (0..3).map(|k| u[k] * v[k]).sum();
            worst = worst.max(sin.atan2(cos).to_degrees());
        }
    }
    worst
}

/// A copy of the set's images in a new folder with `table` as `name` instead of the CSV.
fn copy_with_table(from: &Path, name: &str, table: &str) -> tempfile::TempDir {
    let to = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "png") {
            std::fs::copy(&path, to.path().join(path.file_name().unwrap())).unwrap();
        }
    }
    std::fs::write(to.path().join(name), table).unwrap();
    to
}

/// The set's CSV rows as (name, direction) in the project's frame, as written.
fn csv_rows(dir: &Path) -> Vec<(String, [f64; 3])> {
    let text = std::fs::read_to_string(dir.join("light_directions.csv")).unwrap();
    (text.lines())
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split(',').map(str::trim).collect();
            let v = [1, 2, 3].map(|k| f[k].parse::<f64>().unwrap());
            (f[0].to_string(), v)
        })
        .collect()
}

#[test]
fn an_lp_table_reconstructs_the_normals_of_the_csv_it_was_written_from() {
    // Lights all round the view axis, so that a wrong y would show.
    let set = tempfile::tempdir().unwrap();
    let lights = synth::light_rings(8, 15.0, 45.0);
    synth::write_set(set.path(), &Scene::bump(64), &lights, &Capture::default()).unwrap();
    let truth = synth::read_truth(set.path()).unwrap();
    let rows = csv_rows(set.path());
    assert_eq!(rows.len(), 8);

    // As RTIBuilder leaves it: paths before the names, CRLF, trailing blanks, a blank line.
    let with_paths: Vec<(String, [f64; 3])> = (rows.iter())
        .map(|(n, v)| (format!("./jpeg-exports/{n}"), *v))
        .collect();
    let table = lp::format(&with_paths)
        .lines()
        .map(|l| format!("{l}  \r\n"))
        .collect::<Vec<_>>()
        .join("\r\n");
    assert!(
        table.starts_with("8  \r\n\r\n./jpeg-exports/im1.png "),
        "{table}"
    );
    let lp_dir = copy_with_table(set.path(), "capture.lp", &table);

    let from_csv = run(set.path());
    let from_lp = run(lp_dir.path());
    assert_eq!(from_lp.lights, from_csv.lights);
    let worst = max_angle_deg(&from_csv, &from_lp);
    assert!(worst < 1e-6, "normals differ by up to {worst}°");
    let acc = metrics::accuracy(&from_lp, &truth, &truth.mask);
    assert!(acc.mean_deg < 0.05, "{acc:?}");

    // The frame: the same numbers with y taken as the project's (down) instead of up give
    // the mirror image's normals, far from the truth.
    let unflipped: Vec<(String, [f64; 3])> = (rows.iter())
        .map(|(n, [x, y, z])| (n.clone(), [*x, -y, *z]))
        .collect();
    let wrong_dir = copy_with_table(set.path(), "capture.lp", &lp::format(&unflipped));
    let wrong = run(wrong_dir.path());
    let acc = metrics::accuracy(&wrong, &truth, &truth.mask);
    assert!(acc.mean_deg > 1.0, "{acc:?}");
}

#[test]
fn the_committed_bump_set_reads_the_same_from_an_lp_file() {
    let bump = Path::new(env!("CARGO_MANIFEST_DIR")).join("res/bump");
    let rows = csv_rows(&bump);
    // Written by hand as the tools write it: y up.
    let mut table = format!("{}\n", rows.len());
    for (name, [x, y, z]) in &rows {
        table += &format!("{name} {x} {} {z}\n", 0.0 - y);
    }
    assert_eq!(table, lp::format(&rows));
    let lp_dir = copy_with_table(&bump, "bump.lp", &table);
    let worst = max_angle_deg(&run(&bump), &run(lp_dir.path()));
    assert!(worst < 1e-6, "normals differ by up to {worst}°");

    // A folder with both: the CSV is the table, the .lp noted as not read.
    let both = copy_with_table(&bump, "bump.lp", "3\nbroken");
    std::fs::copy(
        bump.join("light_directions.csv"),
        both.path().join("light_directions.csv"),
    )
    .unwrap();
    let set = intake::load_dir(both.path(), DirMask::Folder, &Limits::default()).unwrap();
    assert!(
        (set.notes.iter())
            .any(|n| n == "bump.lp not read: light_directions.csv is the light table"),
        "{:?}",
        set.notes
    );

    // Bad tables are refused, naming the file and line.
    for (text, needles) in [
        (
            "5\nim1.png 0 0 1\nim2.png -0.2 0 1\nim3.png 0.2 0 1\nim4.png 0 0.2 1\n",
            &["bump.lp line 1", "5 lights but 4 rows"][..],
        ),
        (
            "4\nim1.png 0 0 1\nim2.png -0.2 zero 1\nim3.png 0.2 0 1\nim4.png 0 0.2 1\n",
            &["bump.lp line 3", "\"zero\""],
        ),
        (
            "4\nim1.png 0 0 1\nim2.png -0.2 0 1\nim3.png 0 0 0\nim4.png 0 0.2 1\n",
            &["bump.lp line 4", "zero"],
        ),
        (
            "4\nim1.png 0 0 1\nim2.png -0.2 0 1\nim3.png 0.2 0 1\nim4.png nan 0.2 1\n",
            &["bump.lp line 5", "non-finite"],
        ),
    ] {
        let dir = copy_with_table(&bump, "bump.lp", text);
        let e = intake::load_dir(dir.path(), DirMask::Folder, &Limits::default())
            .expect_err("refused")
            .to_string();
        assert!(needles.iter().all(|n| e.contains(n)), "{text:?}: {e}");
    }
    // And the general parser knows an .lp table by its first line.
    assert_eq!(lights::parse(&table).unwrap().len(), 4);
}
