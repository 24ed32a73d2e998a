//! A physical adversarial patch: a square texture fixed in the world, drawn over the rendered
//! observation, so every frame (every query, every arm) sees it at the same place.
//!
//! Conventions: world units are canvas pixels (512 x 512, y down, as [`crate::render`]); the
//! patch's texture is `side x side` RGB u8 in observation pixels, row-major from its top-left
//! corner; its `center` is in world px. In a `W x H` observation the texture's top-left pixel
//! is at `round(center * [W, H] / 512 - side / 2)`, clamped so the whole texture stays inside
//! the frame. The patch lies on top of the scene (a sticker on a transparent sheet over the
//! table): nothing occludes it, which is the worst case for the policy.

use crate::render::CANVAS_SIZE;

/// Why a patch cannot be built or drawn.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PatchError {
    /// The texture's length is not `side * side * 3`.
    #[error("patch texture has {got} bytes: expected side {side} x {side} x 3 = {expected}")]
    Texture {
        /// Side in pixels.
        side: usize,
        /// Bytes given.
        got: usize,
        /// Bytes expected.
        expected: usize,
    },
    /// A side of zero, or a texture larger than the observation.
    #[error(
        "patch side {side} px does not fit a {width} x {height} observation: expected 1..={width}"
    )]
    Side {
        /// Side in pixels.
        side: usize,
        /// Observation width.
        width: usize,
        /// Observation height.
        height: usize,
    },
    /// A centre outside the 512 x 512 world, or not finite.
    #[error("patch centre {center:?} is outside the world: expected each coordinate in [0, 512]")]
    Center {
        /// The rejected centre (world px).
        center: [f64; 2],
    },
    /// An observation buffer whose length is not `width * height * 3`.
    #[error("observation has {got} bytes: expected {width} x {height} x 3")]
    Frame {
        /// Bytes given.
        got: usize,
        /// Width.
        width: usize,
        /// Height.
        height: usize,
    },
}

/// A square patch in the world.
#[derive(Debug, Clone, PartialEq)]
pub struct Patch {
    rgb: Vec<u8>,
    side: usize,
    center: [f64; 2],
}

impl Patch {
    /// A patch of `side x side` RGB pixels (`rgb`, row-major) centred at `center` (world px).
    pub fn new(rgb: Vec<u8>, side: usize, center: [f64; 2]) -> Result<Self, PatchError> {
        if rgb.len() != side * side * 3 {
            return Err(PatchError::Texture {
                side,
                got: rgb.len(),
                expected: side * side * 3,
            });
        }
        let world = CANVAS_SIZE as f64;
        if !center
            .iter()
            .all(|c| c.is_finite() && (0.0..=world).contains(c))
        {
            return Err(PatchError::Center { center });
        }
        if side == 0 {
            return Err(PatchError::Side {
                side,
                width: 0,
                height: 0,
            });
        }
        Ok(Patch { rgb, side, center })
    }

    /// Texture side (observation px).
    pub fn side(&self) -> usize {
        self.side
    }

    /// Centre (world px).
    pub fn center(&self) -> [f64; 2] {
        self.center
    }

    /// The texture, RGB u8 row-major.
    pub fn rgb(&self) -> &[u8] {
        &self.rgb
    }

    /// Top-left pixel `(x, y)` of the texture in a `width x height` observation.
    pub fn origin(&self, width: usize, height: usize) -> Result<(usize, usize), PatchError> {
        if self.side > width || self.side > height {
            return Err(PatchError::Side {
                side: self.side,
                width,
                height,
            });
        }
        Ok((
            origin_px(self.center[0], width, self.side),
            origin_px(self.center[1], height, self.side),
        ))
    }

    /// Draw the patch into an RGB u8 observation (`width * height * 3`, row-major).
    pub fn draw(&self, frame: &mut [u8], width: usize, height: usize) -> Result<(), PatchError> {
        if frame.len() != width * height * 3 {
            return Err(PatchError::Frame {
                got: frame.len(),
                width,
                height,
            });
        }
        let (x0, y0) = self.origin(width, height)?;
        let row = self.side * 3;
        for r in 0..self.side {
            let dst = ((y0 + r) * width + x0) * 3;
            frame[dst..dst + row].copy_from_slice(&self.rgb[r * row..(r + 1) * row]);
        }
        Ok(())
    }
}

/// `round(c * size / 512 - side / 2)`, clamped to `[0, size - side]`.
pub fn origin_px(c: f64, size: usize, side: usize) -> usize {
    let v = (c * size as f64 / CANVAS_SIZE as f64 - side as f64 / 2.0).round();
    v.clamp(0.0, (size - side) as f64) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_exactly_its_square_where_the_world_says() {
        let side = 4;
        let rgb: Vec<u8> = (0..side * side * 3).map(|i| i as u8).collect();
        // World centre (256, 128) -> observation (48, 24) in 96 x 96 -> top-left (46, 22).
        let p = Patch::new(rgb.clone(), side, [256.0, 128.0]).expect("patch");
        assert_eq!(p.origin(96, 96), Ok((46, 22)));
        let mut frame = vec![7u8; 96 * 96 * 3];
        p.draw(&mut frame, 96, 96).expect("draw");
        let mut changed = 0;
        for y in 0..96 {
            for x in 0..96 {
                let inside = (46..50).contains(&x) && (22..26).contains(&y);
                let px = &frame[(y * 96 + x) * 3..][..3];
                if inside {
                    let t = ((y - 22) * side + (x - 46)) * 3;
                    assert_eq!(px, &rgb[t..t + 3], "({x}, {y})");
                    changed += 1;
                } else {
                    assert_eq!(px, &[7, 7, 7], "({x}, {y}) outside the patch");
                }
            }
        }
        assert_eq!(changed, side * side);
    }

    #[test]
    fn stays_inside_the_frame_at_the_world_edge() {
        let p = Patch::new(vec![0; 8 * 8 * 3], 8, [512.0, 0.0]).expect("patch");
        assert_eq!(p.origin(96, 96), Ok((88, 0)));
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        assert!(matches!(
            Patch::new(vec![0; 10], 2, [0.0, 0.0]),
            Err(PatchError::Texture { expected: 12, .. })
        ));
        assert!(matches!(
            Patch::new(vec![0; 12], 2, [f64::NAN, 0.0]),
            Err(PatchError::Center { .. })
        ));
        let p = Patch::new(vec![0; 12], 2, [1.0, 1.0]).expect("patch");
        assert!(matches!(
            p.draw(&mut [0; 5], 96, 96),
            Err(PatchError::Frame { got: 5, .. })
        ));
        let big = Patch::new(vec![0; 100 * 100 * 3], 100, [1.0, 1.0]).expect("patch");
        assert!(matches!(big.origin(96, 96), Err(PatchError::Side { .. })));
    }
}
