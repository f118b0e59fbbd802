//! The Fig. 4 histogram as PNG. Drawn by hand on an `image` buffer with a built-in 5×7
//! pixel font: chart crates need a font file for text, and a file that renders the same
//! bytes everywhere must not depend on the fonts a machine has.

use crate::trials::{COLORS, Histogram};
use anyhow::Context;
use std::path::Path;

/// 5×7 glyphs, one byte a row, the five low bits left to right.
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '+' => [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00],
        '-' => [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00],
        '.' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        _ => [0; 7],
    }
}

struct Canvas {
    img: image::RgbImage,
}

impl Canvas {
    fn rect(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: [u8; 3]) {
        let (w, h) = (i64::from(self.img.width()), i64::from(self.img.height()));
        for y in y0.max(0)..y1.min(h) {
            for x in x0.max(0)..x1.min(w) {
                self.img.put_pixel(x as u32, y as u32, image::Rgb(c));
            }
        }
    }

    /// Text at `(x, y)` (top left), each font pixel `scale` pixels; `center` centres it on x.
    fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, center: bool) {
        let width = s.chars().count() as i64 * 6 * scale;
        let x0 = if center { x - width / 2 } else { x };
        for (i, ch) in s.chars().enumerate() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        let px = x0 + (i as i64 * 6 + col) * scale;
                        let py = y + row as i64 * scale;
                        self.rect(px, py, px + scale, py + scale, [30, 30, 30]);
                    }
                }
            }
        }
    }
}

/// Write the histogram of sutures to failure per policy as a PNG.
pub fn histogram_png(path: &Path, h: &Histogram) -> anyhow::Result<()> {
    let (w, ht) = (900i64, 520i64);
    let (left, right, top, bottom) = (70i64, 20i64, 50i64, 120i64);
    let mut c = Canvas {
        img: image::RgbImage::from_pixel(w as u32, ht as u32, image::Rgb([255, 255, 255])),
    };
    let groups = h.counts.first().map_or(1, Vec::len) as i64;
    let most = i64::from(h.counts.iter().flatten().copied().max().unwrap_or(1).max(1));
    let plot_h = ht - top - bottom;
    let y = |v: i64| top + plot_h - plot_h * v / most;
    c.text(w / 2, 14, "SUTURES TO FAILURE BY POLICY", 2, true);
    for t in 0..=most {
        let yy = y(t);
        c.rect(left, yy, w - right, yy + 1, [220, 220, 220]);
        c.text(
            left - 10 - 12 * t.to_string().len() as i64,
            yy - 7,
            &t.to_string(),
            2,
            false,
        );
    }
    let gw = (w - left - right) / groups;
    let bw = (gw * 8 / 10) / (h.policies.len().max(1) as i64);
    for k in 0..groups {
        let gx = left + gw * k + gw / 10;
        for (p, counts) in h.counts.iter().enumerate() {
            let v = i64::from(counts[k as usize]);
            let x = gx + bw * p as i64;
            c.rect(x, y(v), x + bw - 1, y(0), COLORS[p % COLORS.len()]);
        }
        c.text(left + gw * k + gw / 2, y(0) + 8, &k.to_string(), 2, true);
    }
    c.rect(left, y(0), w - right, y(0) + 2, [30, 30, 30]);
    c.text(
        left + (w - left - right) / 2,
        y(0) + 32,
        "SUTURES TO FAILURE",
        2,
        true,
    );
    c.text(8, top - 30, "TRIALS", 2, false);
    // The legend, entries side by side, wrapping to a new line at the right edge.
    let (mut x, mut yy) = (left, ht - 56);
    for (p, name) in h.policies.iter().enumerate() {
        let width = 20 + 12 * name.chars().count() as i64 + 24;
        if x + width > w - right && x > left {
            x = left;
            yy += 24;
        }
        c.rect(x, yy, x + 14, yy + 14, COLORS[p % COLORS.len()]);
        c.text(x + 20, yy, name, 2, false);
        x += width;
    }
    c.img
        .save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("cannot write {}", path.display()))
}
