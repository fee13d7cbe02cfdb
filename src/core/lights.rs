//! The light table: `file name, x, y, z`, `file name, x, y, z, intensity` or
//! `file name, x, y, z, r, g, b` per row (the seed's CSV), or the same as JSON with
//! `"intensity": 0.8` or `"intensity": [r, g, b]`, or the relighting tools' `.lp` ([`lp`]).
//! Vectors are normalised here; the intensity (default 1) is kept apart.
//!
//! A JSON light may give its `position` instead of a direction (a near light: an LED of a
//! dome or a ring; [`Emitter`]), with an optional `axis` and `anisotropy`; the table's top
//! level may then carry the `camera`, the working `distance` and the positions' `unit`
//! ([`Rig`], read by [`parse_table`]).

pub mod lp;

use serde::{Deserialize, Serialize};

use super::camera::Pinhole;
use super::error::InputError;

/// Rec. 709 luminance weights for R, G, B.
pub const LUMA_WEIGHTS: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// A light's brightness as a table gives it: one value, or one per colour channel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Intensity {
    One(f64),
    Rgb([f64; 3]),
}

/// One image's light: a unit direction (seed frame) and a relative intensity.
#[derive(Debug, Clone, PartialEq)]
pub struct Light {
    pub name: String,
    /// For a near light, the direction from the scene's centre (on the optical axis at the
    /// working distance) to the light: what a distant table would say.
    pub direction: [f64; 3],
    /// The scalar the solve uses. For an RGB intensity this is the Rec. 709 luminance of
    /// `rgb` (right for a gray image), until intake meets the image in colour: it then
    /// divides each channel by its own intensity and rescales the result by
    /// min(r, g, b), which becomes this value.
    pub intensity: f64,
    /// The per-channel intensities, when the table gives them.
    pub rgb: Option<[f64; 3]>,
    /// Where the light is, when the table gives its position (a near light).
    pub emitter: Option<Emitter>,
}

/// A light at a finite distance: its direction and irradiance change across the scene.
/// Radiance towards a point `X` is `intensity · max(0, −l·axis)^anisotropy / r²` with
/// `r = |position − X|`, `l = (position − X) / r`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Emitter {
    /// Camera frame (x right, y down, z towards the camera; the scene lies at z < 0), in
    /// the table's unit.
    pub position: [f64; 3],
    /// The LED's unit principal direction, towards the scene; None: isotropic.
    pub axis: Option<[f64; 3]>,
    /// μ ≥ 0 of the falloff off the axis (0 without an axis).
    pub anisotropy: f64,
    /// Whether the table gave the intensity; an LED's unknown intensity is estimated
    /// from the object itself.
    pub intensity_known: bool,
}

/// What a near-light table says beside its lights: the camera, the working distance to
/// the object along the optical axis and the unit of positions and distance.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Rig {
    pub camera: Option<Pinhole>,
    pub distance: Option<f64>,
    pub unit: Option<String>,
}

/// A light table with what its top level says.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    pub lights: Vec<Light>,
    pub rig: Rig,
}

impl Table {
    /// Whether any light is given by its position.
    pub fn is_near(&self) -> bool {
        self.lights.iter().any(|l| l.emitter.is_some())
    }
}

impl Light {
    /// The light as the solve sees it: direction scaled by intensity.
    pub fn scaled(&self) -> [f64; 3] {
        self.direction.map(|c| c * self.intensity)
    }
}

/// Longest light table accepted (rows); far above any real rig, it bounds parsing work.
pub const MAX_ROWS: usize = 10_000;

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

/// What every table must be, whatever its layout: no name twice, at least 3 rows.
pub fn check_table(lights: &[Light]) -> Result<(), InputError> {
    check_duplicates(lights)?;
    if lights.len() < 3 {
        return Err(InputError::TooFewImages {
            count: lights.len(),
        });
    }
    Ok(())
}

/// Longest light name (bytes).
pub const MAX_NAME_BYTES: usize = 255;

/// Whether `name` can be a light's name in a CSV table and read back as itself: not
/// empty, at most [`MAX_NAME_BYTES`], no `,` (the field separator), `#` (a comment), `"`,
/// control characters, or space at either end. The reason, if not.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("a name is empty".into());
    }
    if name.len() > MAX_NAME_BYTES {
        return Err(format!("a name is longer than {MAX_NAME_BYTES} bytes"));
    }
    if let Some(c) = name
        .chars()
        .find(|c| matches!(c, ',' | '#' | '"') || c.is_control())
    {
        return Err(format!(
            "{name:?} contains {c:?}: a light name cannot hold a comma, #, a quote or a control character"
        ));
    }
    if name.trim() != name {
        return Err(format!("{name:?} starts or ends with a space"));
    }
    Ok(())
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

fn parse_csv(text: &str) -> Result<Vec<Light>, InputError> {
    let mut lights = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let row = i + 1;
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        if lights.len() >= MAX_ROWS {
            return Err(InputError::Lights(format!("more than {MAX_ROWS} rows")));
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if ![4, 5, 7].contains(&fields.len()) {
            return Err(InputError::LightRow {
                row,
                reason: format!(
                    "expected `name, x, y, z`, `name, x, y, z, intensity` or `name, x, y, z, r, g, b`, found {} fields",
                    fields.len()
                ),
            });
        }
        let name = fields[0];
        let number = |idx: usize, what: &str| -> Result<f64, InputError> {
            fields[idx]
                .parse::<f64>()
                .map_err(|_| InputError::LightRow {
                    row,
                    reason: format!("{what} of {name:?} is not a number: {:?}", fields[idx]),
                })
        };
        let v = [number(1, "x")?, number(2, "y")?, number(3, "z")?];
        let intensity = match fields.len() {
            5 => Some(Intensity::One(number(4, "intensity")?)),
            7 => Some(Intensity::Rgb([
                number(4, "intensity r")?,
                number(5, "intensity g")?,
                number(6, "intensity b")?,
            ])),
            _ => None,
        };
        lights.push(make_light(row, name, v, intensity)?);
    }
    Ok(lights)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonLight {
    name: String,
    #[serde(default)]
    direction: Option<[f64; 3]>,
    #[serde(default)]
    position: Option<[f64; 3]>,
    #[serde(default)]
    axis: Option<[f64; 3]>,
    #[serde(default)]
    anisotropy: Option<f64>,
    #[serde(default)]
    intensity: Option<Intensity>,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum JsonTable {
    List(Vec<JsonLight>),
    Object {
        lights: Vec<JsonLight>,
        #[serde(default)]
        camera: Option<Pinhole>,
        #[serde(default)]
        distance: Option<f64>,
        #[serde(default)]
        unit: Option<String>,
    },
}

/// Longest `unit` text (bytes).
const MAX_UNIT_BYTES: usize = 32;

fn parse_json(text: &str) -> Result<Table, InputError> {
    let table: JsonTable = serde_json::from_str(text).map_err(|e| {
        InputError::Lights(format!(
            "invalid JSON (expected [{{\"name\", \"direction\": [x, y, z] or \"position\": [x, y, z], \"intensity\"?: i or [r, g, b]}}, ...], or {{\"lights\": [...], \"camera\"?, \"distance\"?, \"unit\"?}}): {e}"
        ))
    })?;
    let (rows, rig) = match table {
        JsonTable::List(rows) => (rows, Rig::default()),
        JsonTable::Object {
            lights,
            camera,
            distance,
            unit,
        } => (
            lights,
            Rig {
                camera,
                distance,
                unit,
            },
        ),
    };
    if rows.len() > MAX_ROWS {
        return Err(InputError::Lights(format!("more than {MAX_ROWS} rows")));
    }
    check_rig(&rig)?;
    let lights = (rows.into_iter().enumerate())
        .map(|(i, r)| json_light(i + 1, r, &rig))
        .collect::<Result<Vec<_>, _>>()?;
    let near = lights.iter().filter(|l| l.emitter.is_some()).count();
    if near > 0 && near < lights.len() {
        return Err(InputError::Lights(format!(
            "{near} of {} lights are given by position and the others by direction: give \
             every light the same way",
            lights.len()
        )));
    }
    // The camera may come from the table or from whoever runs the table (a flag, a job's
    // option): the caller asks for it where it is needed (as it does the distance).
    Ok(Table { lights, rig })
}

fn check_rig(rig: &Rig) -> Result<(), InputError> {
    if let Some(d) = rig.distance
        && !(d.is_finite() && d > 0.0 && d < 1e12)
    {
        return Err(InputError::Lights(format!(
            "distance must be a positive number (the working distance along the optical axis), got {d}"
        )));
    }
    if let Some(unit) = &rig.unit
        && (unit.len() > MAX_UNIT_BYTES || unit.chars().any(char::is_control))
    {
        return Err(InputError::Lights(format!(
            "unit must be short text without control characters (at most {MAX_UNIT_BYTES} bytes), got {unit:?}"
        )));
    }
    if let Some(c) = &rig.camera {
        c.check_values()
            .map_err(|e| InputError::Lights(e.to_string()))?;
    }
    Ok(())
}

/// One JSON row: a direction, or a position with its axis and anisotropy.
fn json_light(row: usize, r: JsonLight, rig: &Rig) -> Result<Light, InputError> {
    let bad = |reason: String| InputError::LightRow { row, reason };
    let name = &r.name;
    let Some(position) = r.position else {
        if r.axis.is_some() || r.anisotropy.is_some() {
            return Err(bad(format!(
                "{name:?} has an axis or anisotropy but no position: only near lights have them"
            )));
        }
        let Some(direction) = r.direction else {
            return Err(bad(format!(
                "{name:?} has neither a direction nor a position"
            )));
        };
        return make_light(row, name, direction, r.intensity);
    };
    if r.direction.is_some() {
        return Err(bad(format!(
            "{name:?} has both a direction and a position: give one"
        )));
    }
    if position.iter().any(|c| !c.is_finite() || c.abs() > 1e12) {
        return Err(bad(format!(
            "position of {name:?} is not finite: {position:?}"
        )));
    }
    if position[2] > 0.0 {
        return Err(bad(format!(
            "{name:?} is behind the camera (z = {} > 0; the scene lies at negative z)",
            position[2]
        )));
    }
    let axis = match r.axis {
        None => None,
        Some(a) => {
            let len = a.iter().map(|c| c * c).sum::<f64>().sqrt();
            if !(len.is_finite() && len > 1e-12) {
                return Err(bad(format!("axis of {name:?} is not a direction: {a:?}")));
            }
            Some(a.map(|c| c / len))
        }
    };
    let anisotropy = r.anisotropy.unwrap_or(0.0);
    if !(anisotropy.is_finite() && (0.0..=1000.0).contains(&anisotropy)) {
        return Err(bad(format!(
            "anisotropy of {name:?} must be between 0 and 1000, got {anisotropy}"
        )));
    }
    if anisotropy > 0.0 && axis.is_none() {
        return Err(bad(format!("{name:?} has an anisotropy but no axis")));
    }
    // The direction a distant table would give: from the scene's centre to the light.
    let centre = [0.0, 0.0, -rig.distance.unwrap_or(0.0)];
    let towards = [0, 1, 2].map(|k| position[k] - centre[k]);
    let intensity_known = r.intensity.is_some();
    let mut light = make_light(row, name, towards, r.intensity)?;
    light.emitter = Some(Emitter {
        position,
        axis,
        anisotropy,
        intensity_known,
    });
    Ok(light)
}

/// A table as JSON that [`parse`] reads back to the same lights (for tables read from
/// another layout and stored for later).
pub fn to_json(lights: &[Light]) -> Vec<u8> {
    let rows: Vec<serde_json::Value> = lights
        .iter()
        .map(|l| {
            let intensity = match l.rgb {
                Some(rgb) => Intensity::Rgb(rgb),
                None => Intensity::One(l.intensity),
            };
            serde_json::json!({"name": l.name, "direction": l.direction, "intensity": intensity})
        })
        .collect();
    serde_json::to_vec(&rows).expect("lights serialise")
}

/// Rec. 709 luminance of an RGB intensity: the scalar for a gray image under that light.
pub fn luminance(rgb: [f64; 3]) -> f64 {
    (0..3).map(|c| f64::from(LUMA_WEIGHTS[c]) * rgb[c]).sum()
}

/// One row's light from its parts, checked; `row` (1-based) goes into the error.
pub fn make_light(
    row: usize,
    name: &str,
    v: [f64; 3],
    intensity: Option<Intensity>,
) -> Result<Light, InputError> {
    let bad = |reason: String| InputError::LightRow { row, reason };
    if name.is_empty() {
        return Err(bad("the file name is empty".into()));
    }
    if let Some(c) = v.iter().find(|c| !c.is_finite()) {
        return Err(bad(format!(
            "light vector of {name:?} has a non-finite component ({c})"
        )));
    }
    let norm = v.iter().map(|c| c * c).sum::<f64>().sqrt();
    // Components up to 1e150 square without overflow; anything larger is not a direction.
    if !norm.is_finite() || norm > 1e150 {
        return Err(bad(format!("light vector of {name:?} is too large: {v:?}")));
    }
    if norm < 1e-12 {
        return Err(bad(format!("light vector of {name:?} is zero: {v:?}")));
    }
    let check = |what: &str, i: f64| {
        if !i.is_finite() || i <= 0.0 || i > 1e6 {
            return Err(bad(format!(
                "{what} of {name:?} must be a positive number up to 1e6, got {i}"
            )));
        }
        Ok(i)
    };
    let (intensity, rgb) = match intensity.unwrap_or(Intensity::One(1.0)) {
        Intensity::One(i) => (check("intensity", i)?, None),
        Intensity::Rgb([r, g, b]) => {
            let rgb = [
                check("intensity r", r)?,
                check("intensity g", g)?,
                check("intensity b", b)?,
            ];
            (luminance(rgb), Some(rgb))
        }
    };
    Ok(Light {
        name: name.to_string(),
        direction: v.map(|c| c / norm),
        intensity,
        rgb,
        emitter: None,
    })
}

/// A light given on its own (e.g. for re-shading): three finite numbers, not all zero.
pub fn check_direction(v: [f64; 3]) -> Result<[f64; 3], InputError> {
    make_light(1, "light", v, None)
        .map(|l| l.direction)
        .map_err(|e| match e {
            InputError::LightRow { reason, .. } => InputError::Lights(reason),
            other => other,
        })
}

/// Refuse light sets whose normals cannot be solved reliably.
pub fn check_solvable(lights: &[Light], max_condition: f64) -> Result<f64, InputError> {
    let (condition, rank) = conditioning(lights);
    if rank < 3 {
        return Err(InputError::RankDeficient { rank });
    }
    if condition > max_condition {
        return Err(InputError::IllConditioned {
            condition,
            limit: max_condition,
        });
    }
    Ok(condition)
}

fn check_duplicates(lights: &[Light]) -> Result<(), InputError> {
    let mut seen = std::collections::HashMap::new();
    for (i, l) in lights.iter().enumerate() {
        if let Some(first) = seen.insert(l.name.as_str(), i + 1) {
            return Err(InputError::DuplicateName {
                name: l.name.clone(),
                first,
                second: i + 1,
            });
        }
    }
    Ok(())
}

/// Condition number and numerical rank of the stacked (scaled) light matrix, from the
/// eigenvalues of LᵀL.
pub fn conditioning(lights: &[Light]) -> (f64, usize) {
    let mut m = [[0.0f64; 3]; 3];
    for l in lights {
        let s = l.scaled();
        for (r, row) in m.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v += s[r] * s[c];
            }
        }
    }
    let eig = super::lambert::sym3_eigenvalues(&m);
    let max = eig[2].max(0.0);
    let rank = eig.iter().filter(|&&e| e > max * 1e-12 && e > 0.0).count();
    let min = eig[0].max(0.0);
    let cond = if min > 0.0 {
        (max / min).sqrt()
    } else {
        f64::INFINITY
    };
    (cond, rank)
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
