//! Image files: PNG frames and animated GIFs of RGB u8 HWC buffers.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use anyhow::{Context, Result, ensure};

/// Write an RGB u8 HWC image as PNG.
pub fn write_png(path: &Path, rgb: &[u8], width: usize, height: usize) -> Result<()> {
    ensure!(
        rgb.len() == width * height * 3,
        "image buffer does not match {width}x{height} RGB"
    );
    let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(BufWriter::new(file), width as u32, height as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc
        .write_header()
        .with_context(|| format!("writing {}", path.display()))?;
    w.write_image_data(rgb)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// An animated GIF being written frame by frame (looping, fixed frame delay).
pub struct Gif {
    enc: gif::Encoder<BufWriter<File>>,
    width: u16,
    height: u16,
    delay_cs: u16,
}

impl Gif {
    /// Create `path` for `width` x `height` frames shown `delay_cs` hundredths of a second each.
    pub fn create(path: &Path, width: usize, height: usize, delay_cs: u16) -> Result<Self> {
        let (w, h) = (u16::try_from(width)?, u16::try_from(height)?);
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let mut enc = gif::Encoder::new(BufWriter::new(file), w, h, &[])
            .with_context(|| format!("writing {}", path.display()))?;
        enc.set_repeat(gif::Repeat::Infinite)?;
        Ok(Gif {
            enc,
            width: w,
            height: h,
            delay_cs,
        })
    }

    /// Append one RGB u8 HWC frame (quantised to 256 colours per frame).
    pub fn push(&mut self, rgb: &[u8]) -> Result<()> {
        ensure!(
            rgb.len() == usize::from(self.width) * usize::from(self.height) * 3,
            "GIF frame does not match {}x{} RGB",
            self.width,
            self.height
        );
        let mut frame = gif::Frame::from_rgb_speed(self.width, self.height, rgb, 10);
        frame.delay = self.delay_cs;
        self.enc.write_frame(&frame)?;
        Ok(())
    }
}
