//! The `.lp` light table of the relighting tools (RTIBuilder, RelightLab, the PTM and HSH
//! fitters): a first line with the count N, then N rows `name x y z`, whitespace
//! separated. The name is an image file, often with a path (`./jpeg-exports/img_001.jpg`,
//! `C:\capture\img_001.jpg`); only its file name is kept, and the images are matched by
//! it. CRLF, trailing blanks and blank lines are fine; a name cannot hold spaces (the
//! tools split a row into exactly four fields).
//!
//! **Frame.** The vector points at the light as seen through the camera: x right, **y
//! up**, z towards the camera (HP Labs' PTM fitter documents it so; RelightLab computes
//! its directions from a sphere's highlight with the image's y inverted). The project's y
//! is the image row, down, so a row is read as (x, −y, z), and [`format`] writes (x, −y, z)
//! of a project-frame direction.

use std::fmt::Write;

use super::light::{Light, MAX_ROWS, check_table, make_light};
use crate::core::error::InputError;

/// The file extension (compared without case).
pub const EXTENSION: &str = "lp";

/// Whether a file name is an `.lp` table's (`lights.lp`, `Capture.LP`).
pub fn is_lp_name(name: &str) -> bool {
    name.rsplit_once('.')
        .is_some_and(|(stem, ext)| !stem.is_empty() && ext.eq_ignore_ascii_case(EXTENSION))
}

/// Whether `text` reads as an `.lp` table: its first non-blank line is a whole number.
/// No other table starts so (a CSV row has at least 4 fields, JSON starts with `[` or
/// `{`), so [`super::parse`] tells them apart by this alone.
pub fn is_lp(text: &str) -> bool {
    first_line(strip_bom(text)).is_some_and(|(_, line)| is_count(line))
}

/// Parse an `.lp` table; `file` names it in errors (a file name, or `.lp`).
pub fn parse(file: &str, text: &str) -> Result<Vec<Light>, InputError> {
    let lights = read(file, text)?;
    check_table(&lights)?;
    Ok(lights)
}

/// [`parse`] of a file's bytes, refusing text that is not UTF-8.
pub fn parse_bytes(file: &str, bytes: &[u8]) -> Result<Vec<Light>, InputError> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        InputError::Lights(format!(
            "{file} is not valid UTF-8 text (invalid byte at offset {})",
            e.valid_up_to()
        ))
    })?;
    parse(file, text)
}

/// Write directions given in the project's frame (x right, y down, z towards the camera)
/// as an `.lp` table in the tools' frame: the count, then `name x y z` per row, y negated.
/// Numbers are written in full (the shortest text that reads back to the same value), so
/// [`parse`] gives exactly the lights a CSV of the same vectors gives. Vectors are
/// written as given: the tools expect unit directions, so pass unit vectors (calibrated
/// directions are). Names are written as given: a name with spaces makes a table the
/// tools refuse.
pub fn format(rows: &[(String, [f64; 3])]) -> String {
    let mut out = format!("{}\n", rows.len());
    for (name, [x, y, z]) in rows {
        // `0.0 - y` and `+ 0.0`: a zero component is written `0`, not `-0`.
        writeln!(out, "{name} {} {} {}", x + 0.0, 0.0 - y, z + 0.0).expect("writes to a String");
    }
    out
}

fn strip_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

/// The first non-blank line, trimmed, with its 1-based number.
fn first_line(text: &str) -> Option<(usize, &str)> {
    numbered_lines(text).next()
}

/// The non-blank lines, trimmed (a CR of CRLF included), with their 1-based numbers.
fn numbered_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty())
}

fn is_count(line: &str) -> bool {
    !line.is_empty() && line.bytes().all(|b| b.is_ascii_digit())
}

/// The rows as lights in the project's frame, each checked; the table as a whole is not.
fn read(file: &str, text: &str) -> Result<Vec<Light>, InputError> {
    let at =
        |line: usize, reason: String| InputError::Lights(format!("{file} line {line}: {reason}"));
    let mut lines = numbered_lines(strip_bom(text));
    let Some((count_line, first)) = lines.next() else {
        return Err(InputError::Lights(format!(
            "{file} is empty: expected the number of lights on the first line, then `name x y z` rows"
        )));
    };
    if !is_count(first) {
        return Err(at(
            count_line,
            format!(
                "expected the number of lights (the first line of an .lp file), found {first:?}"
            ),
        ));
    }
    let count = match first.parse::<usize>() {
        Ok(n) if n <= MAX_ROWS => n,
        _ => {
            return Err(at(
                count_line,
                format!("{first} lights is over the limit of {MAX_ROWS}"),
            ));
        }
    };
    let mut lights = Vec::with_capacity(count);
    for (line, row) in lines {
        if lights.len() == count {
            return Err(at(
                line,
                format!("a row more than the {count} lights line {count_line} announces"),
            ));
        }
        let fields: Vec<&str> = row.split_whitespace().collect();
        let [path, x, y, z] = fields[..] else {
            return Err(at(
                line,
                format!(
                    "expected `name x y z` (4 fields separated by spaces; names cannot hold spaces), found {} fields",
                    fields.len()
                ),
            ));
        };
        // Only the file name: the images are matched by it, wherever the tool kept them.
        let name = path.rsplit(['/', '\\']).next().unwrap_or(path);
        let number = |what: &str, f: &str| {
            f.parse::<f64>()
                .map_err(|_| at(line, format!("{what} of {name:?} is not a number: {f:?}")))
        };
        let v = [number("x", x)?, number("y", y)?, number("z", z)?];
        // y up in the file, down the rows in the project (`0.0 - y`: a 0 read stays +0,
        // as [`format`] writes a zero y).
        let light =
            make_light(line, name, [v[0], 0.0 - v[1], v[2]], None).map_err(|e| match e {
                InputError::LightRow { reason, .. } => at(line, reason),
                other => other,
            })?;
        lights.push(light);
    }
    if lights.len() != count {
        return Err(at(
            count_line,
            format!("announces {count} lights but {} rows follow", lights.len()),
        ));
    }
    Ok(lights)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> String {
        parse("t.lp", text).unwrap_err().to_string()
    }

    #[test]
    fn reads_rows_in_the_projects_frame_by_file_name() {
        let t = "\u{feff}3\r\n./jpeg-exports/a.jpg 0.1 0.2 1 \r\n\r\nC:\\shots\\b.jpg\t-0.3 -0.4 1\r\nc.jpg 0 0 2\r\n\r\n";
        let l = parse("t.lp", t).unwrap();
        let names: Vec<&str> = l.iter().map(|l| l.name.as_str()).collect();
        assert_eq!(names, ["a.jpg", "b.jpg", "c.jpg"]);
        let n = (0.01f64 + 0.04 + 1.0).sqrt();
        // y up in the file is up the image: negative y, towards row 0, in the project.
        let want = [0.1 / n, -0.2 / n, 1.0 / n];
        assert!(
            (0..3).all(|k| (l[0].direction[k] - want[k]).abs() < 1e-15),
            "{:?}",
            l[0]
        );
        assert!(l[1].direction[1] > 0.0, "y −0.4 (down) is down the rows");
        assert_eq!(l[2].direction, [0.0, 0.0, 1.0]);
        assert!(l.iter().all(|l| l.intensity == 1.0 && l.rgb.is_none()));
    }

    #[test]
    fn format_reads_back_to_the_same_directions_with_y_up() {
        let rows: Vec<(String, [f64; 3])> = vec![
            ("im1.png".into(), [0.0, -0.0, 1.0]),
            ("im2.png".into(), [-0.2, 0.1, 1.0]),
            ("im3.png".into(), [0.3, -0.7, 0.648074069840786]),
            ("im4.png".into(), [1e-9, 0.25, 1.0 / 3.0]),
        ];
        let text = format(&rows);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines[..3],
            ["4", "im1.png 0 0 1", "im2.png -0.2 -0.1 1"],
            "y up, no -0"
        );
        assert_eq!(lines[4], "im4.png 0.000000001 -0.25 0.3333333333333333");
        assert!(text.ends_with('\n'));
        // Read back: exactly the lights a CSV of the same vectors gives.
        let back = parse("t.lp", &text).unwrap();
        let csv: String = (rows.iter())
            .map(|(n, [x, y, z])| format!("{n}, {x}, {y}, {z}\n"))
            .collect();
        let from_csv = crate::core::lights::parse(&csv).unwrap();
        for (a, b) in back.iter().zip(&from_csv) {
            assert_eq!(a, b);
            // To the last bit (but for the sign of a zero: `-0` is written `0`).
            let bits = |d: [f64; 3]| d.map(|c| (c + 0.0).to_bits());
            assert_eq!(bits(a.direction), bits(b.direction));
        }
        // Through the general parser too, which knows the table by its first line.
        assert_eq!(crate::core::lights::parse(&text).unwrap(), back);
    }

    #[test]
    fn tells_lp_from_the_other_tables() {
        assert!(is_lp("3\na 0 0 1"));
        assert!(is_lp("\u{feff}\r\n  12 \r\n"));
        for other in [
            "a.png, 0, 0, 1",
            "# 3\n3",
            "[]",
            "3 lights\n",
            "-3\n",
            "",
            "\n\n",
        ] {
            assert!(!is_lp(other), "{other:?}");
        }
        assert!(is_lp_name("lights.lp") && is_lp_name("RTI.LP") && is_lp_name("a.b.Lp"));
        assert!(!is_lp_name(".lp") && !is_lp_name("lp") && !is_lp_name("a.lps"));
    }

    #[test]
    fn errors_name_the_file_line_and_value() {
        const OK: &str = "a.jpg 0 0 1\nb.jpg 1 0 1\nc.jpg 0 1 1\n";
        for (text, needles) in [
            (
                format!("4\n{OK}"),
                &["t.lp line 1", "announces 4 lights but 3 rows"][..],
            ),
            (
                format!("2\n{OK}"),
                &[
                    "t.lp line 4",
                    "a row more than the 2 lights line 1 announces",
                ],
            ),
            (
                format!("\n3 lights\n{OK}"),
                &["t.lp line 2", "number of lights", "\"3 lights\""],
            ),
            (
                "3\na.jpg 0 0 1\nb.jpg 1 q 1\nc.jpg 0 1 1".into(),
                &["t.lp line 3", "y of \"b.jpg\"", "\"q\""],
            ),
            (
                "3\na.jpg 0 0 1\nb.jpg NaN 0 1\nc.jpg 0 1 1".into(),
                &["t.lp line 3", "non-finite"],
            ),
            (
                "3\na.jpg 0 0 1\n\nb.jpg 0 0 0\nc.jpg 0 1 1".into(),
                &["t.lp line 4", "\"b.jpg\"", "zero"],
            ),
            (
                "3\na.jpg 0 0 1\nmy b.jpg 1 0 1\nc.jpg 0 1 1".into(),
                &["t.lp line 3", "found 5 fields"],
            ),
            (
                "3\na.jpg 0 0 1\nb.jpg 1 0\nc.jpg 0 1 1".into(),
                &["t.lp line 3", "found 3 fields"],
            ),
            (
                "3\na.jpg 0 0 1\nshots/ 1 0 1\nc.jpg 0 1 1".into(),
                &["t.lp line 3", "file name is empty"],
            ),
            (
                "99999999999999999999999\n".into(),
                &["t.lp line 1", "over the limit"],
            ),
            ("".into(), &["t.lp is empty"]),
            (
                "3\nx/a.jpg 0 0 1\ny/a.jpg 1 0 1\nc.jpg 0 1 1".into(),
                &["\"a.jpg\"", "twice"],
            ),
            ("2\na.jpg 0 0 1\nb.jpg 1 0 1".into(), &["at least 3"]),
        ] {
            let e = err(&text);
            assert!(needles.iter().all(|n| e.contains(n)), "{text:?}: {e}");
        }
        let e = parse_bytes("t.lp", b"3\n\xff").unwrap_err().to_string();
        assert!(e.contains("t.lp") && e.contains("UTF-8"), "{e}");
        // Unnamed, through the general parser.
        let e = crate::core::lights::parse("3\na 0 0 1\nb 1 x 1\nc 0 1 1")
            .unwrap_err()
            .to_string();
        assert!(e.contains(".lp line 3") && e.contains("\"x\""), "{e}");
    }
}
