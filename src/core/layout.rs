//! The folder layouts intake reads, recognised by their file names, and their light
//! tables read into [`Light`]s in the project's frame. Used by folder intake and by the
//! HTTP archive upload alike; it sees names and bytes only, never paths.
//!
//! - The seed's layout: `light_directions.csv` (or `.json`) naming the images.
//! - An `.lp` file of the relighting tools (RTIBuilder, RelightLab), any name: the count,
//!   then `name x y z` rows with **y up**, read as (x, −y, z) ([`lights::lp`]).
//! - The field's benchmark layout: `light_directions.txt`, one `x y z` row per image,
//!   whitespace separated, in a frame with x right, **y up**, z towards the camera; an
//!   optional `light_intensities.txt`, one `r g b` row per image; `filenames.txt`, the
//!   images in the same order, one per line. The project's frame has y = row, **down**,
//!   so each direction is read as (x, −y, z). Without `filenames.txt` the images must be
//!   numbered 1..N or 0..N−1 (`001.png`, `2.png`, …; numeric order) with N the row count.
//!
//! Either layout may hold a `mask.png`; image files its table does not name (a
//! `Normal_gt.png`, say) are ignored with a note, other files silently.

use std::collections::HashSet;

use super::error::InputError;
use super::lights::{self, Intensity, Light};

pub const SEED_CSV: &str = "light_directions.csv";
pub const SEED_JSON: &str = "light_directions.json";
pub const BENCH_DIRECTIONS: &str = "light_directions.txt";
pub const BENCH_INTENSITIES: &str = "light_intensities.txt";
pub const BENCH_NAMES: &str = "filenames.txt";
/// Every file [`read_table`] may read, besides an `.lp` file ([`is_table_file`]).
pub const TABLE_FILES: [&str; 5] = [
    SEED_CSV,
    SEED_JSON,
    BENCH_DIRECTIONS,
    BENCH_INTENSITIES,
    BENCH_NAMES,
];
/// A folder's own mask, in either layout.
pub const MASK: &str = "mask.png";

/// Extensions intake decodes (lower case).
pub const IMAGE_EXTENSIONS: [&str; 7] = ["png", "bmp", "jpg", "jpeg", "tif", "tiff", "exr"];

/// How many ignored names a note lists before it only counts them.
const NOTE_NAMES: usize = 20;

/// The layouts, by their file names, for the error when a folder matches none.
pub const ACCEPTED: &str = "the seed layout (light_directions.csv or light_directions.json naming the images), \
     an .lp file (the relighting tools' table: the count, then `name x y z` rows, y up) \
     or the benchmark layout (light_directions.txt with filenames.txt, optional light_intensities.txt and mask.png; \
     filenames.txt may be left out when the images are numbered 1..N)";

/// A folder's table, read.
#[derive(Debug, Clone)]
pub struct Table {
    /// One per image, in table order, directions in the project's frame.
    pub lights: Vec<Light>,
    /// The folder's own mask file, when it has one the table does not name as an image.
    pub mask: Option<String>,
    /// What was ignored or chosen, for `result.json`.
    pub notes: Vec<String>,
    /// A near-light table's camera, distance and unit.
    pub rig: lights::Rig,
}

/// Whether a file name is one intake would decode as an image.
pub fn is_image(name: &str) -> bool {
    name.rsplit_once('.')
        .is_some_and(|(_, ext)| IMAGE_EXTENSIONS.contains(&ext.to_ascii_lowercase().as_str()))
}

/// Whether [`read_table`] may read a file of this name: one of [`TABLE_FILES`] or an
/// `.lp` file.
pub fn is_table_file(name: &str) -> bool {
    TABLE_FILES.contains(&name) || lights::lp::is_lp_name(name)
}

/// Read the table of the folder whose files are `names` (top level only), with `read`
/// giving a file's bytes by name. `place` names the folder in errors.
pub fn read_table(
    place: &str,
    names: &[String],
    read: &mut dyn FnMut(&str) -> Result<Vec<u8>, InputError>,
) -> Result<Table, InputError> {
    let has = |n: &str| names.iter().any(|m| m == n);
    let mut notes = Vec::new();
    let lp_files: Vec<&str> = (names.iter().map(String::as_str))
        .filter(|n| lights::lp::is_lp_name(n))
        .collect();
    // The other tables a folder holds, each noted as not read.
    let mut not_read = |table: &str, others: &[&str]| {
        for other in others {
            notes.push(format!("{other} not read: {table} is the light table"));
        }
    };
    let mut rig = lights::Rig::default();
    let lights = if let Some(seed) = [SEED_CSV, SEED_JSON].into_iter().find(|n| has(n)) {
        let mut others = lp_files.clone();
        if has(BENCH_DIRECTIONS) {
            others.push(BENCH_DIRECTIONS);
        }
        not_read(seed, &others);
        let table = lights::parse_table_bytes(&read(seed)?)?;
        rig = table.rig;
        table.lights
    } else if let Some(&lp) = lp_files.first() {
        if lp_files.len() > 1 {
            return Err(InputError::Lights(format!(
                "{place} holds {} .lp files ({}): keep only the light table's",
                lp_files.len(),
                lp_files.join(", ")
            )));
        }
        if has(BENCH_DIRECTIONS) {
            not_read(lp, &[BENCH_DIRECTIONS]);
        }
        lights::lp::parse_bytes(lp, &read(lp)?)?
    } else if has(BENCH_DIRECTIONS) {
        let directions = rows(BENCH_DIRECTIONS, &read(BENCH_DIRECTIONS)?)?;
        let intensities = if has(BENCH_INTENSITIES) {
            Some(rows(BENCH_INTENSITIES, &read(BENCH_INTENSITIES)?)?)
        } else {
            None
        };
        let image_names = if has(BENCH_NAMES) {
            file_names(&read(BENCH_NAMES)?)?
        } else {
            numbered_images(names, directions.len())?
        };
        benchmark_lights(&directions, intensities.as_deref(), &image_names)?
    } else {
        return Err(InputError::NoLayout {
            place: place.to_string(),
            accepted: ACCEPTED,
        });
    };

    let named: HashSet<&str> = lights.iter().map(|l| l.name.as_str()).collect();
    let mask = (has(MASK) && !named.contains(MASK)).then(|| MASK.to_string());
    let ignored: Vec<&str> = names
        .iter()
        .map(String::as_str)
        .filter(|n| is_image(n) && !named.contains(n) && mask.as_deref() != Some(*n))
        .collect();
    if !ignored.is_empty() {
        let mut list = ignored[..ignored.len().min(NOTE_NAMES)].join(", ");
        if ignored.len() > NOTE_NAMES {
            list += &format!(" and {} more", ignored.len() - NOTE_NAMES);
        }
        notes.push(format!(
            "ignored {} image file(s) the light table does not name: {list}",
            ignored.len()
        ));
    }
    Ok(Table {
        lights,
        mask,
        notes,
        rig,
    })
}

/// One row of three numbers, with its line number.
type Row = (usize, [f64; 3]);

/// The non-blank lines of a whitespace-separated three-column file.
fn rows(file: &str, bytes: &[u8]) -> Result<Vec<Row>, InputError> {
    let text = utf8(file, bytes)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        if out.len() >= lights::MAX_ROWS {
            return Err(InputError::Lights(format!(
                "{file}: more than {} rows",
                lights::MAX_ROWS
            )));
        }
        let bad = |reason: String| InputError::Lights(format!("{file} row {}: {reason}", i + 1));
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if fields.len() != 3 {
            return Err(bad(format!(
                "expected 3 numbers separated by spaces, found {} fields",
                fields.len()
            )));
        }
        let mut v = [0.0; 3];
        for (k, f) in fields.iter().enumerate() {
            v[k] = f
                .parse()
                .map_err(|_| bad(format!("field {} is not a number: {f:?}", k + 1)))?;
        }
        out.push((i + 1, v));
    }
    Ok(out)
}

fn utf8<'a>(file: &str, bytes: &'a [u8]) -> Result<&'a str, InputError> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        InputError::Lights(format!(
            "{file} is not valid UTF-8 text (invalid byte at offset {})",
            e.valid_up_to()
        ))
    })?;
    Ok(text.trim_start_matches('\u{feff}'))
}

fn file_names(bytes: &[u8]) -> Result<Vec<String>, InputError> {
    Ok(utf8(BENCH_NAMES, bytes)?
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(String::from)
        .collect())
}

/// Without `filenames.txt`: the images numbered 1..N (or 0..N−1), N = `count`, in
/// numeric order; anything else is ambiguous and refused.
fn numbered_images(names: &[String], count: usize) -> Result<Vec<String>, InputError> {
    let mut numbered: Vec<(u64, &String)> = names
        .iter()
        .filter(|n| is_image(n))
        .filter_map(|n| {
            let stem = n.rsplit_once('.')?.0;
            let all_digits = !stem.is_empty() && stem.bytes().all(|b| b.is_ascii_digit());
            all_digits.then(|| stem.parse().ok().map(|k| (k, n)))?
        })
        .collect();
    numbered.sort();
    let first = numbered.first().map_or(0, |(k, _)| *k);
    let consecutive = numbered
        .iter()
        .enumerate()
        .all(|(i, (k, _))| *k == first + i as u64);
    if numbered.len() != count || first > 1 || !consecutive {
        return Err(InputError::Lights(format!(
            "{BENCH_DIRECTIONS} has {count} rows and there is no {BENCH_NAMES} to name their images: \
             without it the images must be numbered 1..{count} (e.g. 001.png), and {} numbered image(s) \
             were found{}; add {BENCH_NAMES}, one image name per line",
            numbered.len(),
            if consecutive {
                ""
            } else {
                " with gaps or repeats"
            },
        )));
    }
    Ok(numbered.into_iter().map(|(_, n)| n.clone()).collect())
}

fn benchmark_lights(
    directions: &[Row],
    intensities: Option<&[Row]>,
    names: &[String],
) -> Result<Vec<Light>, InputError> {
    let count_mismatch = |other: &str, n: usize| {
        InputError::Lights(format!(
            "{BENCH_DIRECTIONS} has {} rows but {other} has {n}: they must have one row per image",
            directions.len()
        ))
    };
    if names.len() != directions.len() {
        return Err(count_mismatch(BENCH_NAMES, names.len()));
    }
    if let Some(i) = intensities
        && i.len() != directions.len()
    {
        return Err(count_mismatch(BENCH_INTENSITIES, i.len()));
    }
    let lights = (directions.iter().zip(names).enumerate())
        .map(|(i, (&(line, [x, y, z]), name))| {
            let rgb = intensities.map(|rows| rows[i]);
            // y up in the file, down the rows in the project.
            lights::make_light(line, name, [x, -y, z], rgb.map(|(_, v)| Intensity::Rgb(v))).map_err(
                |e| match e {
                    InputError::LightRow { reason, .. } => {
                        let (file, line) = match rgb {
                            Some((l, _)) if reason.starts_with("intensity") => {
                                (BENCH_INTENSITIES, l)
                            }
                            _ => (BENCH_DIRECTIONS, line),
                        };
                        InputError::Lights(format!("{file} row {line}: {reason}"))
                    }
                    other => other,
                },
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    lights::check_table(&lights)?;
    Ok(lights)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    fn read_from<'a>(
        files: &'a [(&'a str, &'a str)],
    ) -> impl FnMut(&str) -> Result<Vec<u8>, InputError> + 'a {
        move |n| {
            Ok(files
                .iter()
                .find(|(f, _)| *f == n)
                .map(|(_, t)| t.as_bytes().to_vec())
                .unwrap())
        }
    }

    fn table(files: &[(&str, &str)], extra: &[&str]) -> Result<Table, InputError> {
        let mut all: Vec<&str> = files.iter().map(|(n, _)| *n).collect();
        all.extend_from_slice(extra);
        read_table("test", &names(&all), &mut read_from(files))
    }

    const DIRS: &str = "0.1 0.2 1\n-0.3 0.1 1\n0 -0.4 1\n";

    #[test]
    fn benchmark_rows_flip_y_and_take_rgb_and_names() {
        let t = table(
            &[
                (BENCH_DIRECTIONS, DIRS),
                (BENCH_INTENSITIES, "1 2 4\n1 1 1\n0.5 0.5 0.5\n"),
                (BENCH_NAMES, "a.png\nb.png\nc.png\n\n"),
            ],
            &[
                "a.png",
                "b.png",
                "c.png",
                "mask.png",
                "Normal_gt.png",
                "x.mat",
            ],
        )
        .unwrap();
        let l = &t.lights;
        assert_eq!(l[0].name, "a.png");
        let n = (0.01f64 + 0.04 + 1.0).sqrt();
        assert!((l[0].direction[1] + 0.2 / n).abs() < 1e-12, "{:?}", l[0]);
        assert!((l[0].direction[0] - 0.1 / n).abs() < 1e-12);
        assert!(l[2].direction[1] > 0.0, "y up -0.4 is down the rows");
        assert_eq!(l[0].rgb, Some([1.0, 2.0, 4.0]));
        assert_eq!(t.mask.as_deref(), Some("mask.png"));
        assert_eq!(t.notes.len(), 1, "{:?}", t.notes);
        assert!(t.notes[0].contains("Normal_gt.png") && !t.notes[0].contains("mask"));
    }

    #[test]
    fn numbered_images_stand_in_for_filenames_only_when_unambiguous() {
        let t = table(
            &[(BENCH_DIRECTIONS, DIRS)],
            &["003.png", "001.png", "002.png", "Normal_gt.png"],
        )
        .unwrap();
        let order: Vec<&str> = t.lights.iter().map(|l| l.name.as_str()).collect();
        assert_eq!(order, ["001.png", "002.png", "003.png"]);
        for extra in [
            &["1.png", "2.png"][..],
            &["1.png", "2.png", "4.png"],
            &["1.png", "01.png", "2.png", "3.png"],
        ] {
            let e = table(&[(BENCH_DIRECTIONS, DIRS)], extra)
                .unwrap_err()
                .to_string();
            assert!(e.contains(BENCH_NAMES), "{extra:?}: {e}");
        }
    }

    #[test]
    fn errors_name_the_file_and_row() {
        let e = table(
            &[
                (BENCH_DIRECTIONS, "0 0 1\n1 0 x\n0 1 1\n"),
                (BENCH_NAMES, "a\nb\nc"),
            ],
            &[],
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("light_directions.txt row 2") && e.contains("\"x\""),
            "{e}"
        );
        let e = table(
            &[
                (BENCH_DIRECTIONS, DIRS),
                (BENCH_NAMES, "a\nb\nc"),
                (BENCH_INTENSITIES, "1 1 1\n\n1 0 1\n1 1 1\n"),
            ],
            &[],
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("light_intensities.txt row 3") && e.contains("intensity g"),
            "{e}"
        );
        let e = table(&[(BENCH_DIRECTIONS, DIRS), (BENCH_NAMES, "a\nb")], &[])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("3 rows") && e.contains("filenames.txt has 2"),
            "{e}"
        );
        let e = table(&[], &["a.png", "b.png", "notes.txt"])
            .unwrap_err()
            .to_string();
        for layout in [
            SEED_CSV,
            SEED_JSON,
            BENCH_DIRECTIONS,
            BENCH_NAMES,
            BENCH_INTENSITIES,
        ] {
            assert!(e.contains(layout), "{e}");
        }
        assert!(e.contains(".lp"), "{e}");
    }

    const LP: &str =
        "3\r\n./jpeg-exports/a.png 0.1 0.2 1\r\nb.png -0.3 0.1 1\r\nc.png 0 -0.4 1\r\n";

    #[test]
    fn an_lp_file_is_the_table_after_the_seeds_and_before_the_benchmarks() {
        let t = table(&[("rti.lp", LP)], &["a.png", "b.png", "c.png", "d.png"]).unwrap();
        let from_txt = table(
            &[
                (BENCH_DIRECTIONS, DIRS),
                (BENCH_NAMES, "a.png\nb.png\nc.png"),
            ],
            &[],
        )
        .unwrap();
        // The same y-up frame as the benchmark's rows.
        assert_eq!(t.lights, from_txt.lights);
        assert_eq!(t.notes.len(), 1, "{:?}", t.notes);
        assert!(t.notes[0].contains("d.png"), "{:?}", t.notes);

        let csv = "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n";
        let t = table(
            &[(SEED_CSV, csv), ("rti.lp", LP), (BENCH_DIRECTIONS, DIRS)],
            &[],
        )
        .unwrap();
        assert_eq!(t.lights, lights::parse(csv).unwrap());
        assert!(
            t.notes
                .iter()
                .any(|n| n == "rti.lp not read: light_directions.csv is the light table"),
            "{:?}",
            t.notes
        );
        assert!(
            t.notes
                .iter()
                .any(|n| n.starts_with("light_directions.txt not read")),
            "{:?}",
            t.notes
        );

        let t = table(
            &[
                ("RTI.LP", LP),
                (BENCH_DIRECTIONS, DIRS),
                (BENCH_NAMES, "x\ny\nz"),
            ],
            &[],
        )
        .unwrap();
        assert_eq!(t.lights[0].name, "a.png");
        assert!(
            t.notes
                .iter()
                .any(|n| n == "light_directions.txt not read: RTI.LP is the light table"),
            "{:?}",
            t.notes
        );
        assert!(is_table_file("RTI.LP") && is_table_file(SEED_CSV) && !is_table_file("a.png"));

        let e = table(&[("a.lp", LP), ("b.lp", LP)], &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains("2 .lp files (a.lp, b.lp)"), "{e}");
        let e = table(&[("rti.lp", "3\na.png 0 0 1\nb.png 1 0 1\n")], &[])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rti.lp line 1") && e.contains("3 lights but 2 rows"),
            "{e}"
        );
    }
}
