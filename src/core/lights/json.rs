//! The JSON table: a list of lights, or an object with `lights` and the rig's `camera`,
//! `distance` and `unit`; each light given by its direction, or by its position (a near
//! light) with an optional `axis` and `anisotropy`. And a table written back as JSON.

use serde::Deserialize;

use super::light::{Emitter, Intensity, Light, MAX_ROWS, Rig, Table, make_light};
use crate::core::camera::Pinhole;
use crate::core::error::InputError;

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

pub(super) fn parse_json(text: &str) -> Result<Table, InputError> {
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

/// A table as JSON that `lights::parse` reads back to the same lights (for tables read from
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
