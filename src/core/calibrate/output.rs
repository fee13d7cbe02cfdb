//! What a calibration writes: the light table (the seed's CSV or a `.lp` file), the
//! lights' positions, the per-light quality table, the overlay and the light diagram.

use super::circle::Circle;
use super::draw;
use super::model::Calibration;
use crate::core::outputs::png_bytes;

impl Calibration {
    /// The light table as a `.lp` file (RTIBuilder, RelightLab: y up; no intensities).
    pub fn lp_table(&self) -> String {
        let rows: Vec<(String, [f64; 3])> = self
            .lights
            .iter()
            .map(|l| (l.name.clone(), l.highlight.direction))
            .collect();
        crate::core::lights::lp::format(&rows)
    }

    /// The light table in the seed's format: `name, x, y, z` or `name, x, y, z, intensity`.
    pub fn table(&self) -> String {
        let mut out = String::new();
        for l in &self.lights {
            let d = l.highlight.direction;
            out.push_str(&format!(
                "{}, {:.6}, {:.6}, {:.6}",
                l.name, d[0], d[1], d[2]
            ));
            if let Some(k) = l.intensity {
                out.push_str(&format!(", {k:.4}"));
            }
            out.push('\n');
        }
        out
    }

    /// The light positions (several balls) as a table `name, x, y, z`, in ball radii or,
    /// given the balls' diameter, in its unit; a comment line says which. Lights whose rays
    /// do not meet are left out. None with one ball.
    pub fn positions_table(&self, ball_diameter: Option<f64>) -> Option<String> {
        if self.more_circles.is_empty() {
            return None;
        }
        let (k, unit) = match ball_diameter {
            Some(d) => (d / 2.0, "the unit of the balls' diameter"),
            None => (1.0, "ball radii"),
        };
        let mut out = format!(
            "# light positions in {unit}; x = column right, y = row down, z towards the camera; origin: {}\n",
            match self.camera_is_pinhole {
                true => "the camera",
                false => "the first ball's centre",
            }
        );
        for l in &self.lights {
            if let Some(p) = &l.position {
                let x = p.position.map(|v| v * k);
                out.push_str(&format!(
                    "{}, {:.6}, {:.6}, {:.6}\n",
                    l.name, x[0], x[1], x[2]
                ));
            }
        }
        Some(out)
    }

    /// The per-light quality table, as aligned text.
    pub fn quality_table(&self) -> String {
        let mut out = String::from(
            "  #  image                 name                  highlight x, y    px   peak  clip  rim px  elev °  azim °  conf\n",
        );
        for l in &self.lights {
            let hl = &l.highlight;
            let d = hl.direction;
            let elevation = d[2].clamp(-1.0, 1.0).asin().to_degrees();
            let azimuth = d[1].atan2(d[0]).to_degrees();
            out.push_str(&format!(
                "{:>3}  {:<20}  {:<20}  {:>8.2}, {:>7.2}  {:>4}  {:.3}  {:<4}  {:>6.1}  {:>6.1}  {:>6.1}  {:.2}\n",
                l.index + 1,
                l.image,
                l.name,
                hl.x,
                hl.y,
                hl.pixels,
                hl.peak,
                if hl.clipped { "yes" } else { "no" },
                hl.rim_distance,
                elevation,
                azimuth,
                hl.confidence
            ));
        }
        out
    }

    /// The overlay picture as PNG: the circle and the numbered highlights over the
    /// maximum image.
    pub fn overlay_png(&self) -> Vec<u8> {
        let marks: Vec<draw::Mark> = self
            .lights
            .iter()
            .map(|l| draw::Mark {
                number: l.index + 1,
                x: l.highlight.x,
                y: l.highlight.y,
                confidence: l.highlight.confidence,
            })
            .collect();
        let circles: Vec<Circle> = std::iter::once(self.circle)
            .chain(self.more_circles.iter().copied())
            .collect();
        png_bytes(&draw::overlay(&self.max_image, &circles, &marks))
    }

    /// The light diagram as PNG (`lights.png`).
    pub fn lights_png(&self) -> Vec<u8> {
        let dirs: Vec<(usize, [f64; 3])> = self
            .lights
            .iter()
            .map(|l| (l.index + 1, l.highlight.direction))
            .collect();
        png_bytes(&draw::lights_diagram(&dirs))
    }
}
