//! The seed's CSV table: `file name, x, y, z`, `file name, x, y, z, intensity` or
//! `file name, x, y, z, r, g, b` per row, `#` comments and blank lines skipped.

use super::light::{Intensity, Light, MAX_ROWS, make_light};
use crate::core::error::InputError;

pub(super) fn parse_csv(text: &str) -> Result<Vec<Light>, InputError> {
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
