//! The light table: `file name, x, y, z[, intensity]` per row (the seed's CSV), or the same
//! as JSON. Vectors are normalised here; the intensity (default 1) is kept apart.

use serde::Deserialize;

use super::InputError;

/// One image's light: a unit direction (seed frame) and a relative intensity.
#[derive(Debug, Clone, PartialEq)]
pub struct Light {
    pub name: String,
    pub direction: [f64; 3],
    pub intensity: f64,
}

impl Light {
    /// The light as the solve sees it: direction scaled by intensity.
    pub fn scaled(&self) -> [f64; 3] {
        self.direction.map(|c| c * self.intensity)
    }
}

/// Longest light table accepted (rows); far above any real rig, it bounds parsing work.
pub const MAX_ROWS: usize = 10_000;

/// Parse a light table, CSV or JSON (detected by a leading `[` or `{`).
pub fn parse(text: &str) -> Result<Vec<Light>, InputError> {
    let trimmed = text.trim_start_matches('\u{feff}').trim_start();
    let lights = if trimmed.starts_with('[') || trimmed.starts_with('{') {
        parse_json(trimmed)?
    } else {
        parse_csv(trimmed)?
    };
    check_duplicates(&lights)?;
    if lights.len() < 3 {
        return Err(InputError::TooFewImages {
            count: lights.len(),
        });
    }
    Ok(lights)
}

/// Parse the bytes of a light table, refusing text that is not UTF-8.
pub fn parse_bytes(bytes: &[u8]) -> Result<Vec<Light>, InputError> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        InputError::Lights(format!(
            "not valid UTF-8 text (invalid byte at offset {})",
            e.valid_up_to()
        ))
    })?;
    parse(text)
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
        if !(4..=5).contains(&fields.len()) {
            return Err(InputError::LightRow {
                row,
                reason: format!(
                    "expected `name, x, y, z[, intensity]`, found {} fields",
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
        let intensity = if fields.len() == 5 {
            Some(number(4, "intensity")?)
        } else {
            None
        };
        lights.push(make_light(row, name, v, intensity)?);
    }
    Ok(lights)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonLight {
    name: String,
    direction: [f64; 3],
    #[serde(default)]
    intensity: Option<f64>,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum JsonTable {
    List(Vec<JsonLight>),
    Object { lights: Vec<JsonLight> },
}

fn parse_json(text: &str) -> Result<Vec<Light>, InputError> {
    let table: JsonTable = serde_json::from_str(text).map_err(|e| {
        InputError::Lights(format!(
            "invalid JSON (expected [{{\"name\", \"direction\": [x, y, z], \"intensity\"?}}, ...]): {e}"
        ))
    })?;
    let rows = match table {
        JsonTable::List(rows) | JsonTable::Object { lights: rows } => rows,
    };
    if rows.len() > MAX_ROWS {
        return Err(InputError::Lights(format!("more than {MAX_ROWS} rows")));
    }
    rows.into_iter()
        .enumerate()
        .map(|(i, r)| make_light(i + 1, &r.name, r.direction, r.intensity))
        .collect()
}

fn make_light(
    row: usize,
    name: &str,
    v: [f64; 3],
    intensity: Option<f64>,
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
    let intensity = intensity.unwrap_or(1.0);
    if !intensity.is_finite() || intensity <= 0.0 || intensity > 1e6 {
        return Err(bad(format!(
            "intensity of {name:?} must be a positive number, got {intensity}"
        )));
    }
    Ok(Light {
        name: name.to_string(),
        direction: v.map(|c| c / norm),
        intensity,
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
    let eig = super::solve::sym3_eigenvalues(&m);
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
