//! The pictures a person checks a calibration by: the overlay (fitted outline and
//! numbered highlights over the per-pixel maximum of the images) and the light diagram
//! (directions on the unit hemisphere seen from the camera).

use image::{Rgb, RgbImage};
use ndarray::Array2;

use super::circle::Circle;

const OUTLINE: Rgb<u8> = Rgb([40, 220, 90]);
const LABEL: Rgb<u8> = Rgb([255, 230, 60]);

/// A highlight on the overlay: its number, position and confidence (0..1).
pub struct Mark {
    pub number: usize,
    pub x: f64,
    pub y: f64,
    pub confidence: f64,
}

/// Ring colour by confidence: green when sure, amber when doubtful, red when not.
fn confidence_colour(c: f64) -> Rgb<u8> {
    if c >= 0.7 {
        Rgb([60, 230, 90])
    } else if c >= 0.4 {
        Rgb([255, 170, 30])
    } else {
        Rgb([255, 50, 40])
    }
}

/// The overlay: `max` (the images' maximum, already at gamma 1/2 so the dim sphere
/// shows), the circle, and each highlight ringed in its confidence's colour, labelled
/// with its number and its confidence in percent.
pub fn overlay(max: &Array2<u8>, circles: &[Circle], marks: &[Mark]) -> RgbImage {
    let (h, w) = max.dim();
    let mut img = RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let v = max[[y as usize, x as usize]];
        Rgb([v, v, v])
    });
    for circle in circles {
        ring(&mut img, circle.cx, circle.cy, circle.r, OUTLINE);
        ring(&mut img, circle.cx, circle.cy, 1.5, OUTLINE);
    }
    for m in marks {
        let colour = confidence_colour(m.confidence);
        ring(&mut img, m.x, m.y, 4.0, colour);
        ring(&mut img, m.x, m.y, 5.0, colour);
        text(
            &mut img,
            m.x + 6.0,
            m.y + 4.0,
            &m.number.to_string(),
            LABEL,
            2,
        );
        let percent = (100.0 * m.confidence).round() as u32;
        text(
            &mut img,
            m.x + 6.0,
            m.y + 16.0,
            &percent.to_string(),
            colour,
            1,
        );
    }
    img
}

/// The light diagram: the hemisphere towards the camera as a disc (x right, y down),
/// rings at 30° and 60° from the view axis, each light a numbered dot.
pub fn lights_diagram(directions: &[(usize, [f64; 3])]) -> RgbImage {
    let (size, radius) = (320u32, 140.0);
    let c = (size as f64 - 1.0) / 2.0;
    let mut img = RgbImage::from_pixel(size, size, Rgb([255, 255, 255]));
    let grey = Rgb([170, 170, 170]);
    ring(&mut img, c, c, radius, Rgb([60, 60, 60]));
    for polar in [30f64, 60.0] {
        ring(&mut img, c, c, radius * polar.to_radians().sin(), grey);
    }
    for t in -140..=140 {
        put(&mut img, c + t as f64, c, grey);
        put(&mut img, c, c + t as f64, grey);
    }
    for &(n, d) in directions {
        let (x, y) = (c + radius * d[0], c + radius * d[1]);
        for dy in -2..=2 {
            for dx in -2..=2 {
                put(&mut img, x + dx as f64, y + dy as f64, Rgb([200, 30, 30]));
            }
        }
        text(
            &mut img,
            x + 4.0,
            y + 3.0,
            &n.to_string(),
            Rgb([20, 20, 120]),
            2,
        );
    }
    img
}

fn put(img: &mut RgbImage, x: f64, y: f64, colour: Rgb<u8>) {
    let (x, y) = (x.round(), y.round());
    if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, colour);
    }
}

fn ring(img: &mut RgbImage, cx: f64, cy: f64, r: f64, colour: Rgb<u8>) {
    let steps = (std::f64::consts::TAU * r * 3.0).ceil().max(12.0) as usize;
    for k in 0..steps {
        let a = k as f64 / steps as f64 * std::f64::consts::TAU;
        put(img, cx + r * a.cos(), cy + r * a.sin(), colour);
    }
}

/// Digits in a 3×5 pixel font, drawn `scale`×.
fn text(img: &mut RgbImage, x: f64, y: f64, s: &str, colour: Rgb<u8>, scale: usize) {
    const DIGITS: [[u8; 5]; 10] = [
        [7, 5, 5, 5, 7],
        [2, 6, 2, 2, 7],
        [7, 1, 7, 4, 7],
        [7, 1, 7, 1, 7],
        [5, 5, 7, 1, 1],
        [7, 4, 7, 1, 7],
        [7, 4, 7, 5, 7],
        [7, 1, 1, 1, 1],
        [7, 5, 7, 5, 7],
        [7, 5, 7, 1, 7],
    ];
    let scale = scale.max(1) as f64;
    for (i, ch) in s.chars().enumerate() {
        let Some(d) = ch.to_digit(10) else { continue };
        let glyph = DIGITS[d as usize];
        let ox = x + i as f64 * 4.0 * scale;
        for (row, bits) in glyph.iter().enumerate() {
            for col in 0..3 {
                if bits >> (2 - col) & 1 == 1 {
                    for sy in 0..scale as usize {
                        for sx in 0..scale as usize {
                            put(
                                img,
                                ox + (col as f64) * scale + sx as f64,
                                y + row as f64 * scale + sy as f64,
                                colour,
                            );
                        }
                    }
                }
            }
        }
    }
}
