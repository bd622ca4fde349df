//! Writing RGB images (PNG strips of frames) atomically.

use std::path::Path;

use crate::error::{Error, Result};
use crate::fsutil::write_atomically;

/// An RGB u8 image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<u8>,
}

impl RgbImage {
    /// A black image.
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            pixels: vec![0; width * height * 3],
        }
    }

    /// Copies a `side x side` RGB frame into the image at (`x0`, `y0`), each pixel
    /// drawn as a `scale x scale` block (nearest-neighbour upscaling, so pixels stay visible).
    pub fn blit_scaled(&mut self, frame: &[u8], side: usize, x0: usize, y0: usize, scale: usize) {
        for y in 0..side * scale {
            for x in 0..side * scale {
                let (dx, dy) = (x0 + x, y0 + y);
                if dx >= self.width || dy >= self.height {
                    continue;
                }
                let src = ((y / scale) * side + x / scale) * 3;
                let dst = (dy * self.width + dx) * 3;
                self.pixels[dst..dst + 3].copy_from_slice(&frame[src..src + 3]);
            }
        }
    }

    /// Encodes as PNG.
    pub fn encode_png(&self) -> std::result::Result<Vec<u8>, String> {
        let mut pixmap = tiny_skia::Pixmap::new(self.width as u32, self.height as u32)
            .ok_or_else(|| format!("cannot make a {}x{} image", self.width, self.height))?;
        for (rgba, rgb) in pixmap
            .data_mut()
            .chunks_exact_mut(4)
            .zip(self.pixels.chunks_exact(3))
        {
            rgba.copy_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
        }
        pixmap.encode_png().map_err(|e| e.to_string())
    }

    /// Writes a PNG atomically; refuses to replace an existing file unless `force`.
    pub fn save_png(&self, path: &Path, force: bool) -> Result<()> {
        let bytes = self.encode_png().map_err(|message| Error::Image {
            path: path.to_path_buf(),
            message,
        })?;
        write_atomically(path, force, |w| {
            std::io::Write::write_all(w, &bytes).map_err(|e| Error::io(path, e))
        })
    }
}
