//! The light table: `file name, x, y, z`, `file name, x, y, z, intensity` or
//! `file name, x, y, z, r, g, b` per row (the seed's CSV), or the same as JSON with
//! `"intensity": 0.8` or `"intensity": [r, g, b]`, or the relighting tools' `.lp` ([`lp`]).
//! Vectors are normalised here; the intensity (default 1) is kept apart.
//!
//! A JSON light may give its `position` instead of a direction (a near light: an LED of a
//! dome or a ring; [`Emitter`]), with an optional `axis` and `anisotropy`; the table's top
//! level may then carry the `camera`, the working `distance` and the positions' `unit`
//! ([`Rig`], read by [`parse_table`]).
//!
//! This file is the dispatch over the layouts; below it: `csv`, `json` (which also writes
//! a table back as JSON) and [`lp`], the layouts; `light`, the records and the checks
//! every layout shares; `conditioning`, whether a set of lights can be solved.

mod conditioning;
mod csv;
mod json;
mod light;
pub mod lp;

pub use conditioning::{check_solvable, conditioning};
use csv::parse_csv;
use json::parse_json;
pub use json::to_json;
pub use light::{
    Emitter, Intensity, LUMA_WEIGHTS, Light, MAX_NAME_BYTES, MAX_ROWS, Rig, Table, check_direction,
    check_name, check_table, luminance, make_light,
};

use super::error::InputError;

/// Parse a light table: JSON (detected by a leading `[` or `{`), `.lp` (a first line
/// that is a whole number, [`lp::is_lp`]) or CSV. A near-light table's rig is refused
/// here (its lights need it): read it with [`parse_table`].
pub fn parse(text: &str) -> Result<Vec<Light>, InputError> {
    let table = parse_table(text)?;
    if table.is_near() {
        return Err(InputError::Lights(
            "lights given by position (near lights) are not taken here: give directions".into(),
        ));
    }
    Ok(table.lights)
}

/// Parse a light table with its top level: [`parse`]'s layouts, and JSON lights given by
/// position with the rig's camera, distance and unit (each optional here: a near-light
/// run takes the camera and distance from the table or from its caller).
pub fn parse_table(text: &str) -> Result<Table, InputError> {
    let trimmed = text.trim_start_matches('\u{feff}').trim_start();
    let table = if trimmed.starts_with('[') || trimmed.starts_with('{') {
        parse_json(trimmed)?
    } else if lp::is_lp(text) {
        return Ok(Table {
            lights: lp::parse(".lp", text)?,
            rig: Rig::default(),
        });
    } else {
        Table {
            lights: parse_csv(trimmed)?,
            rig: Rig::default(),
        }
    };
    check_table(&table.lights)?;
    Ok(table)
}

/// Parse the bytes of a light table, refusing text that is not UTF-8.
pub fn parse_bytes(bytes: &[u8]) -> Result<Vec<Light>, InputError> {
    parse(utf8(bytes)?)
}

/// [`parse_table`] of a table's bytes, refusing text that is not UTF-8.
pub fn parse_table_bytes(bytes: &[u8]) -> Result<Table, InputError> {
    parse_table(utf8(bytes)?)
}

fn utf8(bytes: &[u8]) -> Result<&str, InputError> {
    std::str::from_utf8(bytes).map_err(|e| {
        InputError::Lights(format!(
            "not valid UTF-8 text (invalid byte at offset {})",
            e.valid_up_to()
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_seed_format_with_blank_lines_crlf_and_comments() {
        let t = "# rig A\r\ndog1.png, 16, 19, 30\r\ndog2.png,13,16,30 # warm\r\n\r\n dog3.png , -17, 10.5, 26.5, 2\n\n";
        let l = parse(t).unwrap();
        assert_eq!(l.len(), 3);
        assert_eq!(l[0].name, "dog1.png");
        let n: f64 = l[0].direction.iter().map(|c| c * c).sum();
        assert!((n - 1.0).abs() < 1e-12);
        assert_eq!(l[2].intensity, 2.0);
        assert!(
            (l[0].direction[2] - 30.0 / (16f64 * 16.0 + 19.0 * 19.0 + 900.0).sqrt()).abs() < 1e-12
        );
    }

    #[test]
    fn json_forms_match_csv() {
        let csv = parse("a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n").unwrap();
        let list = parse(r#"[{"name":"a.png","direction":[0,0,1]},{"name":"b.png","direction":[1,0,1]},{"name":"c.png","direction":[0,1,1]}]"#).unwrap();
        let obj = parse(r#"{"lights":[{"name":"a.png","direction":[0,0,1]},{"name":"b.png","direction":[1,0,1]},{"name":"c.png","direction":[0,1,1],"intensity":1}]}"#).unwrap();
        assert_eq!(csv, list);
        assert_eq!(csv, obj);
    }

    fn err(text: &str) -> String {
        parse(text).unwrap_err().to_string()
    }

    #[test]
    fn errors_name_the_row_and_value() {
        assert!(err("a.png, 0, 0, 0\nb.png,1,0,1\nc.png,0,1,1").contains("row 1"));
        assert!(err("a.png, 0, 0, 0\nb.png,1,0,1\nc.png,0,1,1").contains("zero"));
        let e = err("a.png, 0, 0, 1\nb.png, x, 0, 1\nc.png,0,1,1");
        assert!(e.contains("row 2") && e.contains("\"x\""), "{e}");
        let e = err("a.png, 0, 0, 1\nb.png, NaN, 0, 1\nc.png,0,1,1");
        assert!(e.contains("row 2") && e.contains("non-finite"), "{e}");
        let e = err("a.png, 0, 0, 1\nb.png, 1e300, 0, 1\nc.png,0,1,1");
        assert!(e.contains("too large"), "{e}");
        let e = err("a.png, 0, 0, 1\nb.png, 1, 0, 1\na.png,0,1,1");
        assert!(e.contains("\"a.png\"") && e.contains("rows 1 and 3"), "{e}");
        let e = err("a.png, 0, 0, 1\nb.png, 1, 0, 1");
        assert!(e.contains("at least 3"), "{e}");
        let e = err("a.png, 0, 0\nb.png, 1, 0, 1\nc.png,0,1,1");
        assert!(e.contains("row 1") && e.contains("3 fields"), "{e}");
        let e = err("a.png, 0, 0, 1, -1\nb.png, 1, 0, 1\nc.png,0,1,1");
        assert!(e.contains("intensity"), "{e}");
        let e = parse_bytes(b"a.png, 0, 0, 1\n\xff\xfe")
            .unwrap_err()
            .to_string();
        assert!(e.contains("UTF-8"), "{e}");
        let e = err(r#"[{"name":"a.png","direction":[0,0]}]"#);
        assert!(e.contains("invalid JSON"), "{e}");
    }

    #[test]
    fn rgb_intensities_in_csv_and_json() {
        let csv = parse("a.png, 0, 0, 1, 1, 2, 4\nb.png, 1, 0, 1, 0.5\nc.png, 0, 1, 1\n").unwrap();
        let json = parse(r#"[{"name":"a.png","direction":[0,0,1],"intensity":[1,2,4]},{"name":"b.png","direction":[1,0,1],"intensity":0.5},{"name":"c.png","direction":[0,1,1]}]"#).unwrap();
        assert_eq!(csv, json);
        assert_eq!(csv[0].rgb, Some([1.0, 2.0, 4.0]));
        assert!((csv[0].intensity - luminance([1.0, 2.0, 4.0])).abs() < 1e-12);
        assert_eq!((csv[1].rgb, csv[1].intensity), (None, 0.5));
        // Stored and read back: the same lights (directions renormalised, to the last bit).
        let back = parse_bytes(&to_json(&csv)).unwrap();
        for (a, b) in back.iter().zip(&csv) {
            assert_eq!((&a.name, a.intensity, a.rgb), (&b.name, b.intensity, b.rgb));
            assert!((0..3).all(|k| (a.direction[k] - b.direction[k]).abs() < 1e-15));
        }
        for (row, needle) in [
            ("a.png, 0, 0, 1, 1, 0, 1", "intensity g"),
            ("a.png, 0, 0, 1, 1, 1, -2", "intensity b"),
            ("a.png, 0, 0, 1, NaN, 1, 1", "intensity r"),
            ("a.png, 0, 0, 1, 1, x, 1", "intensity g"),
        ] {
            let e = err(&format!("b.png, 1, 0, 1\n{row}\nc.png, 0, 1, 1"));
            assert!(e.contains("row 2") && e.contains(needle), "{row}: {e}");
        }
        let e = err("a.png, 0, 0, 1, 1, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1");
        assert!(e.contains("row 1") && e.contains("6 fields"), "{e}");
        let e = err(r#"[{"name":"a.png","direction":[0,0,1],"intensity":[1,0,1]}]"#);
        assert!(e.contains("row 1") && e.contains("intensity g"), "{e}");
    }

    const CAMERA: &str = r#""camera": {"fx": 800, "fy": 800, "cx": 320, "cy": 240}"#;

    fn near_table(lights: &str) -> String {
        format!(r#"{{"lights": [{lights}], {CAMERA}, "distance": 300, "unit": "mm"}}"#)
    }

    #[test]
    fn near_lights_keep_their_positions_and_rig() {
        let t = parse_table(&near_table(
            r#"{"name": "a.png", "position": [0, 0, 0], "axis": [0, 0, -2], "anisotropy": 1.5, "intensity": 0.9},
               {"name": "b.png", "position": [100, 0, -50]},
               {"name": "c.png", "position": [0, -100, -50]}"#,
        ))
        .unwrap();
        assert!(t.is_near());
        assert_eq!(t.rig.distance, Some(300.0));
        assert_eq!(t.rig.unit.as_deref(), Some("mm"));
        assert_eq!(t.rig.camera.map(|c| c.fx), Some(800.0));
        let a = t.lights[0].emitter.unwrap();
        assert_eq!((a.axis, a.anisotropy), (Some([0.0, 0.0, -1.0]), 1.5));
        assert_eq!(t.lights[0].intensity, 0.9);
        // The direction a distant table would give: from the scene's centre (0, 0, −300).
        assert_eq!(t.lights[0].direction, [0.0, 0.0, 1.0]);
        let b = t.lights[1].direction;
        assert!((b[0] / b[2] - 100.0 / 250.0).abs() < 1e-12, "{b:?}");
        assert_eq!(t.lights[1].emitter.unwrap().axis, None);
        // `parse` takes directions only.
        let e = parse(&near_table(
            r#"{"name": "a.png", "position": [0, 0, 0]}, {"name": "b.png", "position": [1, 0, 0]}, {"name": "c.png", "position": [0, 1, 0]}"#,
        ))
        .unwrap_err();
        assert!(e.to_string().contains("by position"), "{e}");
    }

    #[test]
    fn bad_near_tables_are_named() {
        let rows = |first: &str| {
            format!(
                r#"{first}, {{"name": "b.png", "position": [1, 0, -1]}}, {{"name": "c.png", "position": [0, 1, -1]}}"#
            )
        };
        for (first, needle) in [
            (
                r#"{"name": "a.png", "position": [0, 0, 5]}"#,
                "behind the camera",
            ),
            (r#"{"name": "a.png", "direction": [0, 0, 1]}"#, "same way"),
            (
                r#"{"name": "a.png", "position": [0, 0, -1], "direction": [0, 0, 1]}"#,
                "both",
            ),
            (r#"{"name": "a.png"}"#, "neither"),
            (
                r#"{"name": "a.png", "position": [0, 0, -1], "anisotropy": 2}"#,
                "no axis",
            ),
            (
                r#"{"name": "a.png", "position": [0, 0, -1], "axis": [0, 0, 0]}"#,
                "axis",
            ),
            (
                r#"{"name": "a.png", "position": [0, 0, -1], "axis": [0, 0, -1], "anisotropy": -1}"#,
                "anisotropy",
            ),
            (
                r#"{"name": "a.png", "position": [0, 0, -1], "intensity": 0}"#,
                "intensity",
            ),
        ] {
            let e = parse_table(&near_table(&rows(first)))
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{first}: {e}");
        }
        // Neither camera nor distance: the table is read, the rig left for the caller to
        // complete.
        let t = parse_table(&format!(
            r#"{{"lights": [{}]}}"#,
            rows(r#"{"name": "a.png", "position": [0, 0, -1]}"#)
        ))
        .unwrap();
        assert!(t.is_near() && t.rig == Rig::default(), "{t:?}");
        let e = parse_table(&format!(
            r#"{{"lights": [{}], {CAMERA}, "distance": -3}}"#,
            rows(r#"{"name": "a.png", "position": [0, 0, -1]}"#)
        ))
        .unwrap_err()
        .to_string();
        assert!(e.contains("distance"), "{e}");
    }

    #[test]
    fn conditioning_detects_rank_and_spread() {
        let l = parse("a,0,0,1\nb,1,0,1\nc,0,1,1").unwrap();
        let (cond, rank) = conditioning(&l);
        assert_eq!(rank, 3);
        assert!(cond.is_finite() && cond > 1.0);
        let coplanar = parse("a,1,0,1\nb,-1,0,1\nc,0.5,0,1\nd,0,0,1").unwrap();
        let (cond, rank) = conditioning(&coplanar);
        assert_eq!(rank, 2, "cond {cond}");
    }
}
