//! A set on disk: the images, their names and the truth.

use std::path::Path;

use image::{ImageBuffer, Luma};
use ndarray::Array2;

use super::set::ChromeSet;
use crate::core::commit::write_atomic;
use crate::core::error::RunError;
use crate::core::outputs::png_bytes;

/// The folder of a set's true lights and circles.
pub(super) const TRUTH: &str = "truth-lights";

impl ChromeSet {
    /// Write the set: `ball01.png`…, `names.txt` naming the object images `im1.png`… in
    /// the same order, and the truth under `truth-lights/` (not `truth/`: that holds the
    /// maps of the reconstruction sets):
    /// - `light_directions.csv`: `name, x, y, z` from the first ball's centre, then the
    ///   intensity there when `matte` is given;
    /// - `light_directions_ball1.csv`, `…ball2.csv`…: the same from each ball's centre
    ///   (with the intensity there), when there are several balls or near lights;
    /// - `light_positions.csv`: near lights' `name, x, y, z`, pixels;
    /// - `circle.txt`: the first ball's `cx, cy, r`; `circles.txt`: every ball's, a line
    ///   each, the first one first.
    ///
    /// With `matte`, the matte spheres' images go to `<dir>/matte/`.
    pub fn write(&self, dir: &Path, matte: Option<&[f64]>) -> Result<(), RunError> {
        let truth = dir.join(TRUTH);
        create(&truth)?;
        self.write_images(dir, "ball", &self.render())?;
        if let Some(k) = matte {
            let matte_dir = dir.join("matte");
            create(&matte_dir)?;
            self.write_images(&matte_dir, "matte", &self.render_matte(k))?;
        }
        let names: Vec<String> = (1..=self.lights.len())
            .map(|i| format!("im{i}.png"))
            .collect();
        write_atomic(dir, "names.txt", (names.join("\n") + "\n").as_bytes())?;
        let table = |ball: usize| {
            let mut csv = String::new();
            for (i, (name, (l, falloff))) in names.iter().zip(self.truth_from(ball)).enumerate() {
                csv.push_str(&format!("{name}, {}, {}, {}", l[0], l[1], l[2]));
                if let Some(k) = matte {
                    csv.push_str(&format!(", {}", k[i] * falloff));
                }
                csv.push('\n');
            }
            csv
        };
        write_atomic(&truth, "light_directions.csv", table(0).as_bytes())?;
        let balls = self.balls();
        if balls.len() > 1 || self.light_positions.is_some() {
            for b in 0..balls.len() {
                let name = format!("light_directions_ball{}.csv", b + 1);
                write_atomic(&truth, &name, table(b).as_bytes())?;
            }
        }
        if let Some(positions) = &self.light_positions {
            let csv: String = names
                .iter()
                .zip(positions)
                .map(|(name, p)| format!("{name}, {}, {}, {}\n", p[0], p[1], p[2]))
                .collect();
            write_atomic(&truth, "light_positions.csv", csv.as_bytes())?;
        }
        let circles: Vec<String> = balls
            .iter()
            .map(|(c, r)| format!("{}, {}, {}\n", c[0], c[1], r))
            .collect();
        write_atomic(&truth, "circles.txt", circles.concat().as_bytes())?;
        write_atomic(&truth, "circle.txt", circles[0].as_bytes())
    }

    fn write_images(&self, dir: &Path, stem: &str, images: &[Array2<u16>]) -> Result<(), RunError> {
        for (i, img) in images.iter().enumerate() {
            let (h, w) = img.dim();
            let at = |x: u32, y: u32| img[[y as usize, x as usize]];
            let bytes = if self.bit_depth == 8 {
                png_bytes(&ImageBuffer::<Luma<u8>, Vec<u8>>::from_fn(
                    w as u32,
                    h as u32,
                    |x, y| Luma([at(x, y) as u8]),
                ))
            } else {
                png_bytes(&ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(
                    w as u32,
                    h as u32,
                    |x, y| Luma([at(x, y)]),
                ))
            };
            write_atomic(dir, &format!("{stem}{:02}.png", i + 1), &bytes)?;
        }
        Ok(())
    }
}

fn create(dir: &Path) -> Result<(), RunError> {
    std::fs::create_dir_all(dir).map_err(|e| RunError::Output {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })
}
