//! The near-light model: `I = ρ · intensity · max(0, −l·axis)^μ · max(0, n·l) / r²`, with
//! `r = |position − X|` and `l = (position − X) / r` for the surface point `X`.
//!
//! Irradiance is expressed relative to a light of the same intensity at the working
//! distance `reference` (multiplied by `reference²`), so that an albedo solved under near
//! lights reads like one solved under distant lights of the table's intensities.

use crate::core::camera::Pinhole;
use crate::core::error::InputError;
use crate::core::lights::Light;

/// The irradiance vector `s · l` one light casts on the point `x` (camera frame, the
/// table's unit): `l` the unit vector towards the light, `s = intensity ·
/// max(0, −l·axis)^μ · (reference / r)²`. A distant light gives its scaled direction.
#[inline]
pub fn irradiance(light: &Light, x: [f64; 3], reference: f64) -> [f64; 3] {
    let Some(e) = &light.emitter else {
        return light.scaled();
    };
    let v = [0, 1, 2].map(|k| e.position[k] - x[k]);
    let r2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    if r2 <= 0.0 {
        return [0.0; 3];
    }
    let r = r2.sqrt();
    let l = v.map(|c| c / r);
    let cone = match e.axis {
        Some(a) if e.anisotropy > 0.0 => {
            let c = -(l[0] * a[0] + l[1] * a[1] + l[2] * a[2]);
            // In f32: a cone's fall-off needs no more, and f64 `powf` costs more than
            // the rest of the pixel's light vectors.
            if c <= 0.0 {
                0.0
            } else {
                f64::from((c as f32).powf(e.anisotropy as f32))
            }
        }
        _ => 1.0,
    };
    let s = light.intensity * cone * reference * reference / r2;
    l.map(|c| c * s)
}

/// Every light's [`irradiance`] at `x`, as the per-pixel fit takes them.
pub fn light_vectors(lights: &[Light], x: [f64; 3], reference: f64, out: &mut [[f32; 3]]) {
    for (o, l) in out.iter_mut().zip(lights) {
        *o = irradiance(l, x, reference).map(|c| c as f32);
    }
}

/// Refuses a table with an LED that lights nothing the camera sees: one with a cone (an
/// axis and μ > 0) that leaves dark every point of the frame at the working `distance`
/// (the corners, the edges' midpoints and the centre of a `width × height` image), its
/// axis pointing away from the object.
pub fn check_cones(
    lights: &[Light],
    camera: &Pinhole,
    distance: f64,
    (width, height): (usize, usize),
) -> Result<(), InputError> {
    let (w, h) = (
        width.saturating_sub(1) as f64,
        height.saturating_sub(1) as f64,
    );
    let frame: Vec<[f64; 3]> = [0.0, 0.5, 1.0]
        .iter()
        .flat_map(|&u| [0.0, 0.5, 1.0].map(|v| (u * w, v * h)))
        .map(|(x, y)| {
            [
                (x - camera.cx) / camera.fx * distance,
                (y - camera.cy) / camera.fy * distance,
                -distance,
            ]
        })
        .collect();
    for light in lights {
        let Some(e) = &light.emitter else { continue };
        let Some(axis) = e.axis.filter(|_| e.anisotropy > 0.0) else {
            continue;
        };
        let lit = frame.iter().any(|x| {
            let v = [0, 1, 2].map(|k| x[k] - e.position[k]);
            v[0] * axis[0] + v[1] * axis[1] + v[2] * axis[2] > 0.0
        });
        if !lit {
            return Err(InputError::Lights(format!(
                "the LED of {:?} faces away from the object: its axis {axis:?} leaves every \
                 point of the frame at the working distance ({distance}) outside its cone; an \
                 axis points from the LED towards the scene (the scene lies at negative z)",
                light.name
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::lights::{Emitter, make_light};

    fn led(position: [f64; 3], axis: Option<[f64; 3]>, mu: f64) -> Light {
        let mut l = make_light(1, "led", [0.0, 0.0, 1.0], None).unwrap();
        l.emitter = Some(Emitter {
            position,
            axis,
            anisotropy: mu,
            intensity_known: true,
        });
        l
    }

    /// An LED above the frame aimed at it passes; the same aimed back at the camera is
    /// refused, naming it; an isotropic one has no cone to miss.
    #[test]
    fn an_led_facing_away_is_refused() {
        let camera = Pinhole::centred(100.0, 64, 64);
        let at = |axis: [f64; 3], mu: f64| {
            let mut l = led([30.0, 0.0, -20.0], Some(axis), mu);
            l.name = "im7.png".into();
            check_cones(&[l], &camera, 100.0, (64, 64))
        };
        assert!(at([-0.3, 0.0, -1.0], 2.0).is_ok());
        let e = at([0.0, 0.0, 1.0], 2.0).unwrap_err().to_string();
        assert!(e.contains("im7.png") && e.contains("faces away"), "{e}");
        assert!(at([0.0, 0.0, 1.0], 0.0).is_ok());
    }

    /// Straight above at the working distance: the light's own intensity along +z; twice
    /// as far: a quarter; off the LED's axis by 60° with μ = 2: a quarter again.
    #[test]
    fn falloff_and_cone() {
        let x = [0.0, 0.0, -100.0];
        let l = led([0.0, 0.0, 0.0], None, 0.0);
        let v = irradiance(&l, x, 100.0);
        assert!((v[2] - 1.0).abs() < 1e-12 && v[0].abs() < 1e-12, "{v:?}");
        let v = irradiance(&l, [0.0, 0.0, -200.0], 100.0);
        assert!((v[2] - 0.25).abs() < 1e-12, "{v:?}");
        let tilt = 60f64.to_radians();
        let axis = [tilt.sin(), 0.0, -tilt.cos()];
        let v = irradiance(&led([0.0, 0.0, 0.0], Some(axis), 2.0), x, 100.0);
        assert!((v[2] - 0.25).abs() < 1e-12, "{v:?}");
        // Behind the LED's cone: dark.
        let away = [0.0, 0.0, 1.0];
        assert_eq!(
            irradiance(&led([0.0; 3], Some(away), 1.0), x, 100.0),
            [0.0; 3]
        );
    }
}
