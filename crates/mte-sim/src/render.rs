//! gym-pusht's pixels, reproduced: the 512 x 512 canvas and its bilinear downscale.
//!
//! # What is drawn (gym-pusht 0.1.8 `_draw`, pymunk 6.11 debug draw, pygame 2.6 primitives)
//!
//! On a white 512 x 512 canvas (world units are canvas pixels, y down, pixel `(x, y)` is the
//! pixel whose top-left corner is at `(x, y)`):
//!
//! 1. the goal T: both boxes filled [`GOAL_GREEN`], no outline;
//! 2. pymunk's debug draw, in Chipmunk's shape iteration order (dynamic shapes, then static):
//!    the T's bar, then its stem — each filled [`BLOCK_FILL`] then outlined by four "fat
//!    segments" of radius 2 in [`BLOCK_OUTLINE`] — then the agent (disk of radius 15 in
//!    [`AGENT_OUTER`], disk of radius 11 in [`AGENT_INNER`]), then the four walls as fat
//!    segments in [`WALL_GRAY`] (so walls cover the agent where they overlap).
//!
//! Every vertex and centre is rounded to the pixel grid with Python's `round` (ties to even)
//! and rasterised with pygame's own integer algorithms (scanline polygon fill, midpoint circle,
//! Bresenham thick line, including pygame's quirks), so the canvas is bit-exact with
//! gym-pusht's for the same state. Last, pymunk draws each contact of the last physics step
//! as a short red anti-aliased segment ([`CONTACT_RED`], pygame `aaline`); those depend on
//! the physics engine's contact points, so they are drawn only when the caller passes them
//! (the `*_with_contacts` methods).
//!
//! The observation is that canvas resized with OpenCV's `cv2.resize(img, (w, h))`
//! (`INTER_LINEAR`, 11-bit fixed-point weights), reproduced bit-exactly by
//! [`resize_bilinear_u8`].
//!
//! # Performance
//!
//! [`Renderer`] keeps the static part (white, goal, walls) as a template. Per frame it
//! restores, row by row, only the spans the previous frame drew, draws block and agent — for
//! an observation only on the canvas rows the resize reads (two per output row; a primitive's
//! output on a row depends only on that row, so those rows are exact) — and repaints the walls
//! over what it drew. The downscale starts from the cached resized template and recomputes
//! only the output values whose source pixels were drawn, using the template's cached
//! horizontally filtered rows for undrawn source rows. A 96 x 96 observation takes ~25 us on
//! one core (`cargo bench -p mte-sim --bench render`).

use crate::geometry::{AGENT_RADIUS, BAR, Pose, STEM, WALL_RADIUS, WALLS};

/// Side of the full-resolution canvas (px): gym-pusht's `pygame.Surface((512, 512))`.
pub const CANVAS_SIZE: usize = 512;
/// Largest accepted output side (px) for observations, visualisations and resizes.
pub const MAX_IMAGE_SIDE: usize = 4096;
/// Largest accepted channel count for [`resize_bilinear_u8`].
pub const MAX_CHANNELS: usize = 4;

/// Background (RGB).
pub const WHITE: [u8; 3] = [255, 255, 255];
/// Goal T fill: pygame `LightGreen` (RGB).
pub const GOAL_GREEN: [u8; 3] = [144, 238, 144];
/// Block outline: pygame `LightSlateGray` (RGB), the shapes' colour.
pub const BLOCK_OUTLINE: [u8; 3] = [119, 136, 153];
/// Block fill: gym-pusht's `light_color` of [`BLOCK_OUTLINE`], `round(min(1.2 * c, 255))` in
/// float32 with pymunk's rounding `as_int` (RGB).
pub const BLOCK_FILL: [u8; 3] = [143, 163, 184];
/// Agent outer disk: pygame `RoyalBlue` (RGB).
pub const AGENT_OUTER: [u8; 3] = [65, 105, 225];
/// Agent inner disk: `light_color` of [`AGENT_OUTER`] (RGB).
pub const AGENT_INNER: [u8; 3] = [78, 126, 255];
/// Walls: pygame `LightGray` (RGB).
pub const WALL_GRAY: [u8; 3] = [211, 211, 211];
/// The action marker of visualisation frames (RGB).
pub const MARKER_RED: [u8; 3] = [255, 0, 0];
/// Contact segments: pymunk's default `collision_point_color` (RGB).
pub const CONTACT_RED: [u8; 3] = [231, 76, 60];

/// One contact marker as pymunk's debug draw passes it to `draw_segment`: end points `a`, `b`
/// (px). For a Chipmunk contact with points `p1` on body A, `p2` on body B and normal `n`
/// (from A to B): `a = p1 - 2 n`, `b = p2 + 2 n`.
pub type ContactSegment = [[f64; 2]; 2];

/// Radius (px) of the agent's inner disk: gym-pusht draws `round(radius - 4)`.
const AGENT_INNER_RADIUS: f64 = AGENT_RADIUS - 4.0;
/// Pixel coordinates are clamped to this magnitude so that integer arithmetic cannot
/// overflow; anything this far out is off the canvas anyway.
const COORD_LIMIT: i32 = 1 << 20;
/// OpenCV's `INTER_RESIZE_COEF_SCALE`: weights are in units of 1/2048.
const COEF_ONE: f32 = 2048.0;

/// Why a frame could not be produced. Each variant names the offending value.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RenderError {
    /// An image side is zero or larger than [`MAX_IMAGE_SIDE`].
    #[error("image size {width}x{height} is invalid: each side must be in 1..={max} px")]
    InvalidSize {
        /// Requested width (px).
        width: usize,
        /// Requested height (px).
        height: usize,
        /// The largest accepted side (px).
        max: usize,
    },
    /// A channel count outside `1..=MAX_CHANNELS`.
    #[error("channel count {channels} is invalid: must be in 1..={max}")]
    InvalidChannels {
        /// The requested channel count.
        channels: usize,
        /// The largest accepted channel count.
        max: usize,
    },
    /// A buffer whose length does not match the image size it is used for.
    #[error("buffer `{name}` has length {actual}, expected {expected} (height * width * channels)")]
    BufferLength {
        /// Which argument.
        name: &'static str,
        /// The length the sizes require.
        expected: usize,
        /// The length given.
        actual: usize,
    },
}

/// What moves in a frame: everything gym-pusht draws besides the static walls.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scene {
    /// Agent centre (px, y down).
    pub agent: [f64; 2],
    /// Pose of the block's body origin (px, px, rad): the values gym-pusht reports as
    /// `block.position` and the raw (unwrapped) `block.angle`.
    pub block: Pose,
    /// Goal pose (px, px, rad). A [`Renderer`] whose goal differs redraws its template.
    pub goal: Pose,
}

/// Draws gym-pusht frames. Owns the static template, the canvas and the resize tables, so
/// that [`Renderer::observation_into`] allocates nothing once it has seen an output size.
#[derive(Clone, Debug)]
pub struct Renderer {
    goal: Pose,
    /// White + goal T + walls, canvas words, 512 x 512.
    template: Vec<u32>,
    canvas: Canvas,
    /// Wall pixels per canvas row: `wall_spans[wall_rows[y]..wall_rows[y + 1]]`, inclusive x.
    wall_spans: Vec<(i32, i32)>,
    wall_rows: Vec<usize>,
    plan: Option<ObsPlan>,
    /// RGB copy of the canvas for the visualisation's resize.
    rgb: Vec<u8>,
}

impl Renderer {
    /// A renderer for episodes whose goal is `goal` (gym-pusht always uses
    /// [`crate::geometry::GOAL`]). Draws the static template once (a few milliseconds).
    pub fn new(goal: Pose) -> Self {
        let mut walls_only = Canvas::new();
        draw_walls(&mut walls_only);
        let wall = pack(WALL_GRAY);
        let mut wall_spans = Vec::new();
        let mut wall_rows = Vec::with_capacity(CANVAS_SIZE + 1);
        for row in walls_only.px.chunks_exact(CANVAS_SIZE) {
            wall_rows.push(wall_spans.len());
            let mut start: Option<usize> = None;
            for x in 0..=CANVAS_SIZE {
                let is_wall = row.get(x) == Some(&wall);
                match (is_wall, start) {
                    (true, None) => start = Some(x),
                    (false, Some(s)) => {
                        wall_spans.push((s as i32, x as i32 - 1));
                        start = None;
                    }
                    _ => {}
                }
            }
        }
        wall_rows.push(wall_spans.len());
        let mut r = Renderer {
            goal,
            template: vec![0; CANVAS_SIZE * CANVAS_SIZE],
            canvas: Canvas::new(),
            wall_spans,
            wall_rows,
            plan: None,
            rgb: Vec::new(),
        };
        r.rebuild_template(goal);
        r
    }

    /// The goal the template was drawn for.
    pub fn goal(&self) -> Pose {
        self.goal
    }

    fn rebuild_template(&mut self, goal: Pose) {
        self.goal = goal;
        let mut c = Canvas::new();
        for poly in [BAR, STEM] {
            let (xs, ys) = rounded_polygon(&goal, &poly);
            fill_poly(&mut c, &xs, &ys, GOAL_GREEN);
        }
        draw_walls(&mut c);
        self.template.copy_from_slice(&c.px);
        self.canvas.px.copy_from_slice(&c.px);
        self.canvas.clear_dirty();
        self.plan = None;
    }

    /// Draws `scene` on the internal canvas, on every row when `all_rows`, else only on the
    /// rows the current observation plan reads. Afterwards the canvas differs from the
    /// template exactly on the rows and spans recorded in `self.canvas`.
    fn draw(&mut self, scene: &Scene, contacts: &[ContactSegment], all_rows: bool) {
        if !same_pose(&scene.goal, &self.goal) {
            self.rebuild_template(scene.goal);
        }
        // Restore what the previous frame drew.
        let cv = &mut self.canvas;
        let d = cv.dirty;
        if !d.is_empty() {
            for y in d.y0 as usize..=d.y1 as usize {
                if cv.row_dirty(y) {
                    let base = y * CANVAS_SIZE;
                    let (a, b) = (base + cv.row_lo[y] as usize, base + cv.row_hi[y] as usize);
                    cv.px[a..=b].copy_from_slice(&self.template[a..=b]);
                }
            }
        }
        cv.clear_dirty();
        match (&self.plan, all_rows) {
            (Some(plan), false) => cv.row_on.copy_from_slice(&plan.reads_row),
            _ => cv.row_on.fill(true),
        }
        for poly in [BAR, STEM] {
            draw_block_box(cv, &scene.block, &poly);
        }
        let p = [to_px(scene.agent[0]), to_px(scene.agent[1])];
        fill_circle(cv, p[0], p[1], to_px(AGENT_RADIUS), AGENT_OUTER);
        fill_circle(cv, p[0], p[1], to_px(AGENT_INNER_RADIUS), AGENT_INNER);
        // The walls are drawn after the block and agent: repaint them where this frame drew.
        let d = cv.dirty;
        if !d.is_empty() {
            let wall = pack(WALL_GRAY);
            for y in d.y0 as usize..=d.y1 as usize {
                if !cv.row_dirty(y) {
                    continue;
                }
                for &(a, b) in &self.wall_spans[self.wall_rows[y]..self.wall_rows[y + 1]] {
                    let (a, b) = (a.max(cv.row_lo[y]), b.min(cv.row_hi[y]));
                    if a <= b {
                        cv.fill_span(a as usize, y, b as usize, wall);
                    }
                }
            }
        }
        // pymunk draws collision points after all shapes.
        for [a, b] in contacts {
            let p = [a[0], a[1], b[0], b[1]].map(|v| to_px(v) as f32);
            aaline(cv, p[0], p[1], p[2], p[3], CONTACT_RED);
        }
    }

    /// The full-resolution canvas (gym-pusht's `_draw()` surface) as RGB u8, HWC,
    /// `512 * 512 * 3` bytes, row-major from the top-left pixel. No contact segments.
    pub fn canvas_rgb(&mut self, scene: &Scene) -> Vec<u8> {
        self.canvas_rgb_with_contacts(scene, &[])
    }

    /// [`Renderer::canvas_rgb`] with pymunk's contact segments drawn last.
    pub fn canvas_rgb_with_contacts(
        &mut self,
        scene: &Scene,
        contacts: &[ContactSegment],
    ) -> Vec<u8> {
        self.draw(scene, contacts, true);
        let mut out = Vec::with_capacity(CANVAS_SIZE * CANVAS_SIZE * 3);
        self.canvas.to_rgb(&mut out);
        out
    }

    /// The policy observation, gym-pusht's `pixels`: the canvas resized to `width` x `height`
    /// px with `cv2.resize` `INTER_LINEAR` (bit-exact), written to `out` as RGB u8 HWC
    /// (`height * width * 3` bytes, row-major). No contact segments. Allocates only when the
    /// output size differs from the previous call's.
    ///
    /// # Errors
    /// [`RenderError::InvalidSize`] for a zero or oversized side, [`RenderError::BufferLength`]
    /// when `out` is not `height * width * 3` bytes long.
    pub fn observation_into(
        &mut self,
        scene: &Scene,
        width: usize,
        height: usize,
        out: &mut [u8],
    ) -> Result<(), RenderError> {
        self.observation_with_contacts_into(scene, &[], width, height, out)
    }

    /// [`Renderer::observation_into`] with pymunk's contact segments drawn last, as gym-pusht
    /// draws the contacts of its last physics step.
    ///
    /// # Errors
    /// As [`Renderer::observation_into`].
    pub fn observation_with_contacts_into(
        &mut self,
        scene: &Scene,
        contacts: &[ContactSegment],
        width: usize,
        height: usize,
        out: &mut [u8],
    ) -> Result<(), RenderError> {
        check_size(width, height)?;
        check_len("out", out.len(), width * height * 3)?;
        if !same_pose(&scene.goal, &self.goal) {
            self.rebuild_template(scene.goal);
        }
        if self
            .plan
            .as_ref()
            .is_none_or(|p| p.w != width || p.h != height)
        {
            self.plan = Some(ObsPlan::new(&self.template, width, height));
        }
        self.draw(scene, contacts, false);
        if let Some(plan) = self.plan.as_mut() {
            plan.run(&self.canvas, out);
        }
        Ok(())
    }

    /// [`Renderer::observation_into`] into a new `height * width * 3` buffer.
    ///
    /// # Errors
    /// As [`Renderer::observation_into`].
    pub fn observation(
        &mut self,
        scene: &Scene,
        width: usize,
        height: usize,
    ) -> Result<Vec<u8>, RenderError> {
        check_size(width, height)?;
        let mut out = vec![0; width * height * 3];
        self.observation_into(scene, width, height, &mut out)?;
        Ok(out)
    }

    /// The visualisation frame of gym-pusht's `render()` (default 680 x 680): the canvas
    /// resized like the observation, plus, when `action` (target position, px) is given, a
    /// red cross marker as `cv2.drawMarker(MARKER_CROSS)` draws it with gym-pusht's
    /// `markerSize = int(8 / 96 * min(w, h))`, `thickness = int(min(w, h) / 96)`, centred at
    /// `(action / 512 * [height, width])` truncated (sic: x is scaled by the height). RGB u8
    /// HWC, `height * width * 3` bytes. No contact segments.
    ///
    /// The marker matches OpenCV for these axis-aligned lines (a band of half-width
    /// `ceil(t / 2)` plus round caps); where gym-pusht's thickness would be 0 (sides under
    /// 96 px, an OpenCV error there) a 1 px line is drawn.
    ///
    /// # Errors
    /// [`RenderError::InvalidSize`] for a zero or oversized side.
    pub fn visualization(
        &mut self,
        scene: &Scene,
        action: Option<[f64; 2]>,
        width: usize,
        height: usize,
    ) -> Result<Vec<u8>, RenderError> {
        self.visualization_with_contacts(scene, &[], action, width, height)
    }

    /// [`Renderer::visualization`] with pymunk's contact segments drawn on the canvas.
    ///
    /// # Errors
    /// As [`Renderer::visualization`].
    pub fn visualization_with_contacts(
        &mut self,
        scene: &Scene,
        contacts: &[ContactSegment],
        action: Option<[f64; 2]>,
        width: usize,
        height: usize,
    ) -> Result<Vec<u8>, RenderError> {
        check_size(width, height)?;
        self.draw(scene, contacts, true);
        self.canvas.to_rgb(&mut self.rgb);
        let mut out = vec![0; width * height * 3];
        resize_bilinear_u8(
            &self.rgb,
            CANVAS_SIZE,
            CANVAS_SIZE,
            3,
            &mut out,
            width,
            height,
        )?;
        if let Some([ax, ay]) = action {
            let size = width.min(height) as f64;
            let marker = (8.0 / 96.0 * size) as i32;
            let thickness = ((1.0 / 96.0 * size) as i32).max(1);
            let cx = clamp_coord(ax / 512.0 * height as f64);
            let cy = clamp_coord(ay / 512.0 * width as f64);
            let img = Image {
                px: &mut out,
                w: width as i32,
                h: height as i32,
            };
            draw_marker_cross(img, cx, cy, marker, thickness);
        }
        Ok(out)
    }
}

/// Bitwise pose equality (so that a NaN goal does not force a redraw every frame).
fn same_pose(a: &Pose, b: &Pose) -> bool {
    [a.x, a.y, a.theta].map(f64::to_bits) == [b.x, b.y, b.theta].map(f64::to_bits)
}

fn check_size(width: usize, height: usize) -> Result<(), RenderError> {
    if width == 0 || height == 0 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(RenderError::InvalidSize {
            width,
            height,
            max: MAX_IMAGE_SIDE,
        });
    }
    Ok(())
}

fn check_len(name: &'static str, actual: usize, expected: usize) -> Result<(), RenderError> {
    if actual != expected {
        return Err(RenderError::BufferLength {
            name,
            expected,
            actual,
        });
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Coordinates.

/// `f64 -> i32` as `(v as f64) as i32` in C/numpy (truncation toward zero), clamped; NaN maps
/// far off the canvas.
fn clamp_coord(v: f64) -> i32 {
    if v.is_nan() {
        -COORD_LIMIT
    } else {
        v.clamp(-COORD_LIMIT as f64, COORD_LIMIT as f64) as i32
    }
}

/// pymunk's `to_pygame`: Python `round` (half to even), clamped; NaN maps off the canvas.
fn to_px(v: f64) -> i32 {
    clamp_coord(v.round_ties_even())
}

/// Body to world coordinates exactly as Chipmunk's `cpTransformPoint` evaluates them
/// (`a*x + c*y + tx` with `a = cos`, `c = -sin`), so that `.5` ties round the same way.
fn body_to_world(pose: &Pose, v: [f64; 2]) -> [f64; 2] {
    let (s, c) = pose.theta.sin_cos();
    [
        c * v[0] + (-s) * v[1] + pose.x,
        s * v[0] + c * v[1] + pose.y,
    ]
}

/// A box of the T in world coordinates, rounded to pixels and closed (first point repeated,
/// as gym-pusht passes it to `pygame.draw.polygon`).
fn rounded_polygon(pose: &Pose, body: &[[f64; 2]; 4]) -> ([i32; 5], [i32; 5]) {
    let mut xs = [0; 5];
    let mut ys = [0; 5];
    for (i, v) in body.iter().enumerate() {
        let w = body_to_world(pose, *v);
        xs[i] = to_px(w[0]);
        ys[i] = to_px(w[1]);
    }
    xs[4] = xs[0];
    ys[4] = ys[0];
    (xs, ys)
}

// ---------------------------------------------------------------------------------------------
// The canvas and pygame's primitives.

/// Inclusive pixel rectangle; empty when `x0 > x1`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Rect {
    x0: i32,
    y0: i32,
    x1: i32,
    y1: i32,
}

impl Rect {
    const EMPTY: Rect = Rect {
        x0: i32::MAX,
        y0: i32::MAX,
        x1: i32::MIN,
        y1: i32::MIN,
    };

    fn is_empty(&self) -> bool {
        self.x0 > self.x1 || self.y0 > self.y1
    }
}

/// The 512 x 512 surface with pygame's clip rectangle (the whole surface) and a record of the
/// pixels drawn since the last [`Canvas::clear_dirty`].
#[derive(Clone, Debug)]
struct Canvas {
    /// Pixels as little-endian `[r, g, b, 0]` words, row-major.
    px: Vec<u32>,
    /// Bounding rectangle of everything drawn since the last [`Canvas::clear_dirty`].
    dirty: Rect,
    /// Per row, the drawn columns `row_lo[y]..=row_hi[y]` (empty when `lo > hi`).
    row_lo: Vec<i32>,
    row_hi: Vec<i32>,
    /// Rows that drawing may touch; drawing on the others is skipped. Each primitive's output
    /// on a row depends only on that row, so the enabled rows come out exactly as if
    /// everything were drawn (observations enable only the rows the resize reads).
    row_on: Vec<bool>,
}

const SIDE: i32 = CANVAS_SIZE as i32;

/// `[r, g, b]` as a canvas word.
#[inline]
fn pack(c: [u8; 3]) -> u32 {
    u32::from_le_bytes([c[0], c[1], c[2], 0])
}

/// A canvas word as `[r, g, b]`.
#[inline]
fn unpack(p: u32) -> [u8; 3] {
    let b = p.to_le_bytes();
    [b[0], b[1], b[2]]
}

impl Canvas {
    fn new() -> Self {
        Canvas {
            px: vec![pack(WHITE); CANVAS_SIZE * CANVAS_SIZE],
            dirty: Rect::EMPTY,
            row_lo: vec![i32::MAX; CANVAS_SIZE],
            row_hi: vec![i32::MIN; CANVAS_SIZE],
            row_on: vec![true; CANVAS_SIZE],
        }
    }

    /// Forgets what was drawn (after the caller restored it).
    fn clear_dirty(&mut self) {
        let d = self.dirty;
        if !d.is_empty() {
            self.row_lo[d.y0 as usize..=d.y1 as usize].fill(i32::MAX);
            self.row_hi[d.y0 as usize..=d.y1 as usize].fill(i32::MIN);
        }
        self.dirty = Rect::EMPTY;
    }

    /// Fills `x0..=x1` of row `y`, all in range.
    #[inline]
    fn fill_span(&mut self, x0: usize, y: usize, x1: usize, c: u32) {
        let base = y * CANVAS_SIZE;
        self.px[base + x0..=base + x1].fill(c);
    }

    /// pygame `drawhorzlineclipbounding`: a clipped horizontal line, either end first.
    #[inline]
    fn hline(&mut self, x1: i32, y: i32, x2: i32, c: [u8; 3]) {
        if !(0..SIDE).contains(&y) || !self.row_on[y as usize] {
            return;
        }
        let (x1, x2) = if x2 < x1 { (x2, x1) } else { (x1, x2) };
        let (x1, x2) = (x1.max(0), x2.min(SIDE - 1));
        if x2 < 0 || x1 >= SIDE {
            return;
        }
        let yu = y as usize;
        self.row_lo[yu] = self.row_lo[yu].min(x1);
        self.row_hi[yu] = self.row_hi[yu].max(x2);
        let d = &mut self.dirty;
        d.x0 = d.x0.min(x1);
        d.x1 = d.x1.max(x2);
        d.y0 = d.y0.min(y);
        d.y1 = d.y1.max(y);
        self.fill_span(x1 as usize, yu, x2 as usize, pack(c));
    }

    /// pygame `set_at`: one clipped pixel.
    #[inline]
    fn set(&mut self, x: i32, y: i32, c: [u8; 3]) {
        self.hline(x, y, x, c);
    }

    /// Whether row `y` differs from what it was before drawing started.
    #[inline]
    fn row_dirty(&self, y: usize) -> bool {
        self.row_lo[y] <= self.row_hi[y]
    }

    /// The canvas as RGB bytes.
    fn to_rgb(&self, out: &mut Vec<u8>) {
        out.resize(self.px.len() * 3, 0);
        for (o, &p) in out.chunks_exact_mut(3).zip(&self.px) {
            o.copy_from_slice(&unpack(p));
        }
    }
}

/// pygame `draw_fillpoly` (2.6.1): scanline fill over integer vertices, edges taken half-open
/// `[y1, y2)` except on the last row, x intersections truncated toward zero, plus the
/// horizontal edges strictly between the top and bottom rows.
fn fill_poly(cv: &mut Canvas, xs: &[i32], ys: &[i32], c: [u8; 3]) {
    let n = xs.len().min(ys.len());
    if n == 0 {
        return;
    }
    let miny = ys[..n].iter().copied().min().unwrap_or(0);
    let maxy = ys[..n].iter().copied().max().unwrap_or(0);
    if miny == maxy {
        let minx = xs[..n].iter().copied().min().unwrap_or(0);
        let maxx = xs[..n].iter().copied().max().unwrap_or(0);
        cv.hline(minx, miny, maxx, c);
        return;
    }
    let mut xi = [0i32; 8];
    // Rows off the canvas draw nothing; skip them (pygame loops over them in vain).
    for y in miny.max(0)..=maxy.min(SIDE - 1) {
        if !cv.row_on[y as usize] {
            continue;
        }
        let yf = f64::from(y);
        let mut k = 0;
        for i in 0..n {
            let ip = if i == 0 { n - 1 } else { i - 1 };
            let (x1, y1, x2, y2) = if ys[ip] < ys[i] {
                (xs[ip], ys[ip], xs[i], ys[i])
            } else if ys[ip] > ys[i] {
                (xs[i], ys[i], xs[ip], ys[ip])
            } else {
                continue;
            };
            if ((y >= y1) && (y < y2)) || ((y == maxy) && (y2 == maxy)) {
                let (x1, y1, x2, y2) = (f64::from(x1), f64::from(y1), f64::from(x2), f64::from(y2));
                if k < xi.len() {
                    xi[k] = ((yf - y1) * (x2 - x1) / (y2 - y1) + x1) as i32;
                    k += 1;
                }
            }
        }
        let xi = &mut xi[..k];
        xi.sort_unstable();
        for pair in xi.chunks_exact(2) {
            cv.hline(pair[0], y, pair[1], c);
        }
    }
    for i in 0..n {
        let ip = if i == 0 { n - 1 } else { i - 1 };
        let y = ys[i];
        if miny < y && ys[ip] == y && y < maxy {
            cv.hline(xs[i], y, xs[ip], c);
        }
    }
}

/// pygame `draw_circle_filled` (2.6.1): midpoint circle, spans `[x0 - x, x0 + x - 1]`.
fn fill_circle(cv: &mut Canvas, x0: i32, y0: i32, radius: i32, c: [u8; 3]) {
    if radius < 1 {
        return;
    }
    let mut f = 1 - radius;
    let mut ddf_x = 0;
    let mut ddf_y = -2 * radius;
    let mut x = 0;
    let mut y = radius;
    while x < y {
        if f >= 0 {
            y -= 1;
            ddf_y += 2;
            f += ddf_y;
        }
        x += 1;
        ddf_x += 2;
        f += ddf_x + 1;
        if f >= 0 {
            cv.hline(x0 - x, y0 + y - 1, x0 + x - 1, c);
            cv.hline(x0 - x, y0 - y, x0 + x - 1, c);
        }
        cv.hline(x0 - y, y0 + x - 1, x0 + y - 1, c);
        cv.hline(x0 - y, y0 - x, x0 + y - 1, c);
    }
}

/// pygame `sign(x, y)`: the sign of `x`, or `y` when `x` is zero.
fn sign_or(x: i32, y: i32) -> i32 {
    if x > 0 {
        1
    } else if x < 0 {
        -1
    } else {
        y
    }
}

/// pygame `clip_line` (Liang-Barsky on the surface), `false` when nothing is visible.
fn clip_line(x1: &mut i32, y1: &mut i32, x2: &mut i32, y2: &mut i32) -> bool {
    let p1 = *x1 - *x2;
    let p2 = -p1;
    let p3 = *y1 - *y2;
    let p4 = -p3;
    let q1 = *x1;
    let q2 = SIDE - *x1;
    let q3 = *y1;
    let q4 = SIDE - *y1;
    let (ox, oy) = (*x1, *y1);
    let mut nmax = 0.0f64;
    let mut pmin = 1.0f64;
    if (p1 == 0 && q1 < 0) || (p2 == 0 && q2 < 0) || (p3 == 0 && q3 < 0) || (p4 == 0 && q4 < 0) {
        return false;
    }
    for (p, qa, qb, pb) in [(p1, q1, q2, p2), (p3, q3, q4, p4)] {
        if p != 0 {
            let r1 = f64::from(qa) / f64::from(p);
            let r2 = f64::from(qb) / f64::from(pb);
            if p < 0 {
                nmax = nmax.max(r1);
                pmin = pmin.min(r2);
            } else {
                nmax = nmax.max(r2);
                pmin = pmin.min(r1);
            }
        }
    }
    if nmax > pmin {
        return false;
    }
    let half_away = |v: f64| (if v < 0.0 { v - 0.5 } else { v + 0.5 }) as i32;
    *x1 = ox + half_away(f64::from(p2) * nmax);
    *y1 = oy + half_away(f64::from(p4) * nmax);
    *x2 = ox + half_away(f64::from(p2) * pmin);
    *y2 = oy + half_away(f64::from(p4) * pmin);
    true
}

/// pygame `draw_line_width` (2.6.1) for `width > 1`: Bresenham along the major axis, each step
/// painting `width` pixels across it from `-(width - 1) / 2` to `+width / 2` (so a width-4
/// line covers offsets -1..=2). `width == 1` draws plain Bresenham pixels.
fn line_width(cv: &mut Canvas, x1: i32, y1: i32, x2: i32, y2: i32, width: i32, c: [u8; 3]) {
    let (mut x1, mut y1, mut x2, mut y2) = (x1, y1, x2, y2);
    let (end_x, end_y) = (x2, y2);
    let xinc = (x1 - x2).abs() <= (y1 - y2).abs();
    let dx = (x2 - x1).abs();
    let sx = if x1 < x2 { 1 } else { -1 };
    let dy = (y2 - y1).abs();
    let sy = if y1 < y2 { 1 } else { -1 };
    let mut err = (if dx > dy { dx } else { -dy }) / 2;
    if !clip_line(&mut x1, &mut y1, &mut x2, &mut y2) {
        return;
    }
    if width <= 1 {
        // pygame `draw_line`.
        let (ddx, ddy) = ((x2 - x1).abs(), (y2 - y1).abs());
        let (ssx, ssy) = (if x1 < x2 { 1 } else { -1 }, if y1 < y2 { 1 } else { -1 });
        let mut e = (if ddx > ddy { ddx } else { -ddy }) / 2;
        while x1 != x2 || y1 != y2 {
            cv.set(x1, y1, c);
            let e2 = e;
            if e2 > -ddx {
                e -= ddy;
                x1 += ssx;
            }
            if e2 < ddy {
                e += ddx;
                y1 += ssy;
            }
        }
        cv.set(x2, y2, c);
        return;
    }
    let (mut lt, mut rb) = if xinc {
        (x1 - (width - 1) / 2, x1 + width / 2)
    } else {
        (y1 - (width - 1) / 2, y1 + width / 2)
    };
    let column = |cv: &mut Canvas, x: i32, lt: i32, rb: i32| {
        for y in lt..=rb {
            cv.set(x, y, c);
        }
    };
    while sign_or(x1 - x2, sx) != sx || sign_or(y1 - y2, sy) != sy {
        if xinc {
            cv.hline(lt, y1, rb, c);
        } else {
            column(cv, x1, lt, rb);
        }
        let e2 = err;
        if e2 > -dx {
            err -= dy;
            x1 += sx;
            if xinc {
                lt += sx;
                rb += sx;
            }
        }
        if e2 < dy {
            err += dx;
            y1 += sy;
            if !xinc {
                lt += sy;
                rb += sy;
            }
        }
    }
    let inside = |x: i32, y: i32| (0..SIDE).contains(&x) && (0..SIDE).contains(&y);
    if xinc {
        while y1 != end_y && (inside(lt, y1) || inside(rb, y1)) {
            cv.hline(lt, y1, rb, c);
            let e2 = err;
            if e2 > -dx {
                err -= dy;
                lt += sx;
                rb += sx;
            }
            if e2 < dy {
                err += dx;
                y1 += sy;
            }
        }
        cv.hline(lt, y1, rb, c);
    } else {
        while x1 != end_x && (inside(x1, lt) || inside(x1, rb)) {
            column(cv, x1, lt, rb);
            let e2 = err;
            if e2 > -dx {
                err -= dy;
                x1 += sx;
            }
            if e2 < dy {
                err += dx;
                lt += sy;
                rb += sy;
            }
        }
        column(cv, x1, lt, rb);
    }
}

/// pygame `get_antialiased_color` with blending, then `set_at`:
/// `(u8)(b * colour + (1 - b) * background)` in single precision.
fn blend_set(cv: &mut Canvas, x: i32, y: i32, c: [u8; 3], brightness: f32) {
    if !(0..SIDE).contains(&x) || !(0..SIDE).contains(&y) {
        return;
    }
    let bg = unpack(cv.px[y as usize * CANVAS_SIZE + x as usize]);
    let mixed: [u8; 3] = std::array::from_fn(|k| {
        (brightness * f32::from(c[k]) + (1.0 - brightness) * f32::from(bg[k])) as u8
    });
    cv.set(x, y, mixed);
}

/// pygame `draw_aaline` (2.6.1, blend on) in its single-precision arithmetic: Wu's line with
/// one-pixel end caps, clipped one pixel beyond the surface.
fn aaline(cv: &mut Canvas, from_x: f32, from_y: f32, to_x: f32, to_y: f32, c: [u8; 3]) {
    let (dx, dy) = (to_x - from_x, to_y - from_y);
    if f64::from(dx).abs() < 0.0001 && f64::from(dy).abs() < 0.0001 {
        let x = (f64::from(from_x) + 0.5).floor() as i32;
        let y = (f64::from(from_y) + 0.5).floor() as i32;
        blend_set(cv, x, y, c, 1.0);
        return;
    }
    if let Some(line) = WuLine::clipped([from_x, from_y], [to_x, to_y]) {
        line.draw(cv, c);
    }
}

/// Where [`aaline`] clips, on either axis: one pixel beyond the surface.
const WU_LO: f32 = -1.0;
const WU_HI: f32 = WU_LO + SIDE as f32 + 1.0;

/// A line in Wu's (major, minor) coordinates: the major axis is the one the line moves
/// along faster (`steep`: y), and `from[0] < to[0]`.
struct WuLine {
    from: [f32; 2],
    to: [f32; 2],
    gradient: f32,
    steep: bool,
}

impl WuLine {
    /// The segment from `a` to `b` (surface x, y), clipped to `[WU_LO, WU_HI]` on both axes;
    /// `None` when nothing of it is left. pygame's clipping, step for step.
    fn clipped(a: [f32; 2], b: [f32; 2]) -> Option<Self> {
        let steep = (b[0] - a[0]).abs() < (b[1] - a[1]).abs();
        let major = |p: [f32; 2]| if steep { [p[1], p[0]] } else { p };
        let (mut f, mut t) = (major(a), major(b));
        if t[0] - f[0] < 0.0 {
            std::mem::swap(&mut f, &mut t);
        }
        if t[0] <= WU_LO || f[0] >= WU_HI {
            return None;
        }
        let gradient = (t[1] - f[1]) / (t[0] - f[0]);
        if f[0] < WU_LO {
            f[1] += gradient * (WU_LO - f[0]);
            f[0] = WU_LO;
        }
        if t[0] > WU_HI {
            t[1] += gradient * (WU_HI - t[0]);
            t[0] = WU_HI;
        }
        // On the minor axis, the end that leaves first depends on the slope's sign.
        let (lo, hi) = if gradient > 0.0 {
            (&mut f, &mut t)
        } else {
            (&mut t, &mut f)
        };
        if hi[1] <= WU_LO || lo[1] >= WU_HI {
            return None;
        }
        if lo[1] < WU_LO {
            lo[0] += (WU_LO - lo[1]) / gradient;
            lo[1] = WU_LO;
        }
        if hi[1] > WU_HI {
            hi[0] += (WU_HI - hi[1]) / gradient;
            hi[1] = WU_HI;
        }
        // One pixel down so that `as i32` floors; pixels are drawn one higher.
        f[1] += 1.0;
        t[1] += 1.0;
        Some(Self {
            from: f,
            to: t,
            gradient,
            steep,
        })
    }

    /// Blends pixel (major, minor) at `brightness`.
    fn put(&self, cv: &mut Canvas, major: i32, minor: i32, c: [u8; 3], brightness: f32) {
        if self.steep {
            blend_set(cv, minor, major, c, brightness);
        } else {
            blend_set(cv, major, minor, c, brightness);
        }
    }

    /// The two end caps, weighted by how much of their pixel column the line covers, then
    /// the two pixels of each column between them.
    fn draw(&self, cv: &mut Canvas, c: [u8; 3]) {
        let ([fx, fy], [tx, ty], gradient) = (self.from, self.to, self.gradient);
        let mut x_start = fx as i32;
        let y_end = fy + gradient * (x_start as f32 - fx);
        let mut intersect_y = y_end;
        if tx > WU_LO + 1.0 {
            self.cap(cv, x_start, y_end, (1 + x_start) as f32 - fx, c);
            intersect_y += gradient;
            x_start += 1;
        }
        let x_end = f64::from(tx).ceil() as i32;
        if fx < WU_HI - 1.0 {
            let y_end = ty + gradient * (x_end as f32 - tx);
            self.cap(cv, x_end, y_end, (1 - x_end) as f32 + tx, c);
        }
        for x in x_start..x_end {
            let y = intersect_y as i32;
            let brightness = 1.0 - intersect_y + y as f32;
            self.put(cv, x, y - 1, c, brightness);
            if (y as f32) < intersect_y {
                self.put(cv, x, y, c, 1.0 - brightness);
            }
            intersect_y += gradient;
        }
    }

    /// One end cap: the column `x` at minor coordinate `y_end`, covered `x_gap` of a pixel.
    fn cap(&self, cv: &mut Canvas, x: i32, y_end: f32, x_gap: f32, c: [u8; 3]) {
        let brightness = y_end - (y_end as i32) as f32;
        let minor = y_end as i32;
        if ((y_end as i32) as f32) < y_end {
            self.put(cv, x, minor, c, brightness * x_gap);
        }
        self.put(cv, x, minor - 1, c, (1.0 - brightness) * x_gap);
    }
}

/// gym-pusht's `DrawOptions.draw_fat_segment`: a `round(2 * radius)`-wide pygame line, and
/// for widths over 2 a quad offset by the "orthogonal" `(|dy|, |dx|) * radius / len` (sic:
/// built from absolute values, so for some directions it is a skewed parallelogram) and a
/// disk of radius `round(radius)` at each end.
fn fat_segment(cv: &mut Canvas, a: [f64; 2], b: [f64; 2], radius: f64, c: [u8; 3]) {
    let (p1x, p1y) = (to_px(a[0]), to_px(a[1]));
    let (p2x, p2y) = (to_px(b[0]), to_px(b[1]));
    let r = to_px(radius * 2.0).max(1);
    line_width(cv, p1x, p1y, p2x, p2y, r, c);
    if r > 2 {
        let o0 = (p2y - p1y).abs();
        let o1 = (p2x - p1x).abs();
        if o0 == 0 && o1 == 0 {
            return;
        }
        let (f0, f1) = (f64::from(o0), f64::from(o1));
        // Python `(a * a + b * b) ** 0.5` is C `pow`.
        let scale = radius / (f0 * f0 + f1 * f1).powf(0.5);
        let o0 = to_px(f0 * scale);
        let o1 = to_px(f1 * scale);
        let xs = [p1x - o0, p1x + o0, p2x + o0, p2x - o0];
        let ys = [p1y - o1, p1y + o1, p2y + o1, p2y - o1];
        fill_poly(cv, &xs, &ys, c);
        let rr = to_px(radius);
        fill_circle(cv, p1x, p1y, rr, c);
        fill_circle(cv, p2x, p2y, rr, c);
    }
}

/// gym-pusht's `DrawOptions.draw_polygon` for one box of the block: fill in the light colour,
/// then the four edges as fat segments of radius 2 in the base colour.
fn draw_block_box(cv: &mut Canvas, pose: &Pose, body: &[[f64; 2]; 4]) {
    let (xs, ys) = rounded_polygon(pose, body);
    fill_poly(cv, &xs, &ys, BLOCK_FILL);
    let w = body.map(|v| body_to_world(pose, v));
    for i in 0..4 {
        fat_segment(cv, w[i], w[(i + 1) % 4], 2.0, BLOCK_OUTLINE);
    }
}

fn draw_walls(cv: &mut Canvas) {
    for [a, b] in WALLS {
        fat_segment(cv, a, b, WALL_RADIUS, WALL_GRAY);
    }
}

// ---------------------------------------------------------------------------------------------
// The action marker (cv2.drawMarker, MARKER_CROSS, 8-connected lines).

struct Image<'a> {
    px: &'a mut [u8],
    w: i32,
    h: i32,
}

impl Image<'_> {
    fn set(&mut self, x: i32, y: i32, c: [u8; 3]) {
        if (0..self.w).contains(&x) && (0..self.h).contains(&y) {
            let i = 3 * (y as usize * self.w as usize + x as usize);
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }
}

/// `cv2.drawMarker(MARKER_CROSS)`: lines from `c - size/2` to `c + size/2` through the centre.
/// OpenCV draws a thick (> 1) line as a band of half-width `ceil(t / 2)` plus round caps of
/// radius `ceil(t / 2)` (`dx^2 + dy^2 <= r^2`); a 1 px line is the plain pixel run.
fn draw_marker_cross(mut img: Image<'_>, cx: i32, cy: i32, size: i32, thickness: i32) {
    let half = size / 2;
    let hw = (thickness + (thickness & 1)) / 2;
    let lo = -(COORD_LIMIT / 2);
    let hi = COORD_LIMIT / 2;
    let (cx, cy) = (cx.clamp(lo, hi), cy.clamp(lo, hi));
    for horizontal in [true, false] {
        // Band: along the line, `-half..=half`; across it, `-hw..=hw` (0 for 1 px lines).
        let across = if thickness > 1 { hw } else { 0 };
        for a in -half..=half {
            for b in -across..=across {
                let (x, y) = if horizontal {
                    (cx + a, cy + b)
                } else {
                    (cx + b, cy + a)
                };
                img.set(x, y, MARKER_RED);
            }
        }
        if thickness > 1 {
            for end in [-half, half] {
                let (ex, ey) = if horizontal {
                    (cx + end, cy)
                } else {
                    (cx, cy + end)
                };
                for dy in -hw..=hw {
                    for dx in -hw..=hw {
                        if dx * dx + dy * dy <= hw * hw {
                            img.set(ex + dx, ey + dy, MARKER_RED);
                        }
                    }
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// cv2.resize INTER_LINEAR, u8.

/// One output coordinate's two source indices (already clamped) and fixed-point weights
/// (units of 1/2048, OpenCV `saturate_cast<short>(w * 2048)`).
#[derive(Clone, Copy, Debug, Default)]
struct Tap {
    i0: usize,
    i1: usize,
    w0: i32,
    w1: i32,
}

/// OpenCV's tables: `f = (float)((d + 0.5) * scale - 0.5)` with `scale = 1 / (dst / src)`,
/// `s = floor(f)`, weights `round(2048 * (1 - frac))`, `round(2048 * frac)`. Along x a source
/// index outside `[0, src - 2]` is clamped with weight (2048, 0); along y OpenCV keeps the
/// unclamped fraction and only clamps the row indices (`clamp_frac = false`).
fn taps(src: usize, dst: usize, clamp_frac: bool) -> Vec<Tap> {
    let scale = 1.0 / (dst as f64 / src as f64);
    let last = src as i64 - 1;
    (0..dst)
        .map(|d| {
            let mut f = ((d as f64 + 0.5) * scale - 0.5) as f32;
            let mut s = f.floor() as i64;
            f -= s as f32;
            if clamp_frac {
                if s < 0 {
                    f = 0.0;
                    s = 0;
                }
                if s >= last {
                    f = 0.0;
                    s = last;
                }
            }
            let w0 = ((1.0f32 - f) * COEF_ONE).round_ties_even() as i32;
            let w1 = (f * COEF_ONE).round_ties_even() as i32;
            Tap {
                i0: s.clamp(0, last) as usize,
                i1: (s + 1).clamp(0, last) as usize,
                w0,
                w1,
            }
        })
        .collect()
}

/// Horizontal pass of one source row (`cn` interleaved channels) into `out` (`dst_w * cn`).
#[inline]
fn hpass(row: &[u8], xt: &[Tap], cn: usize, out: &mut [i32]) {
    if cn == 3 {
        for (o, t) in out.chunks_exact_mut(3).zip(xt) {
            let (a, b) = (&row[3 * t.i0..3 * t.i0 + 3], &row[3 * t.i1..3 * t.i1 + 3]);
            o[0] = i32::from(a[0]) * t.w0 + i32::from(b[0]) * t.w1;
            o[1] = i32::from(a[1]) * t.w0 + i32::from(b[1]) * t.w1;
            o[2] = i32::from(a[2]) * t.w0 + i32::from(b[2]) * t.w1;
        }
    } else {
        for (o, t) in out.chunks_exact_mut(cn).zip(xt) {
            for k in 0..cn {
                o[k] = i32::from(row[cn * t.i0 + k]) * t.w0 + i32::from(row[cn * t.i1 + k]) * t.w1;
            }
        }
    }
}

/// Vertical pass: OpenCV's `VResizeLinear<uchar, int, short>` rounding,
/// `((b0 * (h0 >> 4)) >> 16) + ((b1 * (h1 >> 4)) >> 16) + 2) >> 2`.
#[inline]
fn vpass(h0: &[i32], h1: &[i32], b0: i32, b1: i32, out: &mut [u8]) {
    for ((o, &a), &b) in out.iter_mut().zip(h0).zip(h1) {
        *o = ((((b0 * (a >> 4)) >> 16) + ((b1 * (b >> 4)) >> 16) + 2) >> 2) as u8;
    }
}

/// `cv2.resize(src, (dst_w, dst_h))` with the default `INTER_LINEAR`, for u8 images of
/// `channels` interleaved channels (HWC, row-major, no padding): bit-exact with OpenCV 4.x's
/// fixed-point path (11-bit weights; also equal to its `INTER_AREA` shortcut for exact 2x
/// downscales). No anti-alias prefilter: a downscale by `k` reads two source rows/columns per
/// output row/column.
///
/// # Errors
/// [`RenderError::InvalidSize`] for a zero or oversized side (source or destination),
/// [`RenderError::InvalidChannels`] outside `1..=4`, [`RenderError::BufferLength`] when a
/// buffer is not `h * w * channels` bytes long.
pub fn resize_bilinear_u8(
    src: &[u8],
    src_w: usize,
    src_h: usize,
    channels: usize,
    dst: &mut [u8],
    dst_w: usize,
    dst_h: usize,
) -> Result<(), RenderError> {
    check_size(src_w, src_h)?;
    check_size(dst_w, dst_h)?;
    if channels == 0 || channels > MAX_CHANNELS {
        return Err(RenderError::InvalidChannels {
            channels,
            max: MAX_CHANNELS,
        });
    }
    check_len("src", src.len(), src_w * src_h * channels)?;
    check_len("dst", dst.len(), dst_w * dst_h * channels)?;
    let xt = taps(src_w, dst_w, true);
    let yt = taps(src_h, dst_h, false);
    let (srow, drow) = (src_w * channels, dst_w * channels);
    let mut h0 = vec![0i32; drow];
    let mut h1 = vec![0i32; drow];
    let (mut r0, mut r1) = (usize::MAX, usize::MAX);
    for (t, out) in yt.iter().zip(dst.chunks_exact_mut(drow)) {
        if r0 != t.i0 {
            if r1 == t.i0 {
                std::mem::swap(&mut h0, &mut h1);
                r1 = usize::MAX;
            } else {
                hpass(&src[t.i0 * srow..(t.i0 + 1) * srow], &xt, channels, &mut h0);
            }
            r0 = t.i0;
        }
        if r1 != t.i1 {
            hpass(&src[t.i1 * srow..(t.i1 + 1) * srow], &xt, channels, &mut h1);
            r1 = t.i1;
        }
        vpass(&h0, &h1, t.w0, t.w1, out);
    }
    Ok(())
}

/// Horizontal pass over canvas words (RGB), destination columns `lo..=hi` only.
#[inline]
fn hpass_words(row: &[u32], xt: &[Tap], lo: usize, hi: usize, out: &mut [i32]) {
    for (dx, t) in xt.iter().enumerate().take(hi + 1).skip(lo) {
        let (a, b) = (unpack(row[t.i0]), unpack(row[t.i1]));
        let o = &mut out[3 * dx..3 * dx + 3];
        for k in 0..3 {
            o[k] = i32::from(a[k]) * t.w0 + i32::from(b[k]) * t.w1;
        }
    }
}

/// The observation resize from the 512 x 512 canvas to one output size. The template's
/// filtered rows and resized image are cached, so a frame only recomputes the output values
/// that read a drawn pixel (same arithmetic as [`resize_bilinear_u8`], hence bit-identical).
#[derive(Clone, Debug)]
struct ObsPlan {
    w: usize,
    h: usize,
    xt: Vec<Tap>,
    yt: Vec<Tap>,
    /// Canvas rows the resize reads (only those are drawn for an observation).
    reads_row: Vec<bool>,
    /// `template_h[slot[r]]`: horizontal pass of template row `r` (rows the resize reads).
    slot: Vec<usize>,
    template_h: Vec<i32>,
    /// The template resized.
    template_out: Vec<u8>,
    h0: Vec<i32>,
    h1: Vec<i32>,
}

impl ObsPlan {
    fn new(template: &[u32], w: usize, h: usize) -> Self {
        let xt = taps(CANVAS_SIZE, w, true);
        let yt = taps(CANVAS_SIZE, h, false);
        let drow = w * 3;
        let mut reads_row = vec![false; CANVAS_SIZE];
        let mut slot = vec![usize::MAX; CANVAS_SIZE];
        let mut template_h = Vec::new();
        let mut n = 0;
        for t in &yt {
            for r in [t.i0, t.i1] {
                reads_row[r] = true;
                if slot[r] == usize::MAX {
                    slot[r] = n;
                    n += 1;
                    template_h.resize(n * drow, 0);
                    let row = &template[r * CANVAS_SIZE..(r + 1) * CANVAS_SIZE];
                    let out = &mut template_h[(n - 1) * drow..n * drow];
                    hpass_words(row, &xt, 0, w - 1, out);
                }
            }
        }
        let mut template_out = vec![0u8; h * drow];
        for (t, out) in yt.iter().zip(template_out.chunks_exact_mut(drow)) {
            let a = &template_h[slot[t.i0] * drow..(slot[t.i0] + 1) * drow];
            let b = &template_h[slot[t.i1] * drow..(slot[t.i1] + 1) * drow];
            vpass(a, b, t.w0, t.w1, out);
        }
        ObsPlan {
            w,
            h,
            xt,
            yt,
            reads_row,
            slot,
            template_h,
            template_out,
            h0: vec![0; drow],
            h1: vec![0; drow],
        }
    }

    /// Resizes the canvas into `out` (`h * w * 3` bytes).
    fn run(&mut self, cv: &Canvas, out: &mut [u8]) {
        out.copy_from_slice(&self.template_out);
        let d = cv.dirty;
        if d.is_empty() {
            return;
        }
        // Output columns that read a drawn column (taps are nondecreasing).
        let lo = self.xt.iter().position(|t| t.i1 >= d.x0 as usize);
        let hi = self.xt.iter().rposition(|t| t.i0 <= d.x1 as usize);
        let (Some(lo), Some(hi)) = (lo, hi) else {
            return;
        };
        if lo > hi {
            return;
        }
        let drow = self.w * 3;
        let (cl, ch) = (3 * lo, 3 * hi + 3);
        let mut rows = (usize::MAX, usize::MAX);
        for (t, o) in self.yt.iter().zip(out.chunks_exact_mut(drow)) {
            let (d0, d1) = (cv.row_dirty(t.i0), cv.row_dirty(t.i1));
            if !d0 && !d1 {
                continue;
            }
            let canvas_row = |r: usize| &cv.px[r * CANVAS_SIZE..(r + 1) * CANVAS_SIZE];
            if d0 && rows.0 != t.i0 {
                if rows.1 == t.i0 {
                    std::mem::swap(&mut self.h0, &mut self.h1);
                    rows.1 = usize::MAX;
                } else {
                    hpass_words(canvas_row(t.i0), &self.xt, lo, hi, &mut self.h0);
                }
                rows.0 = t.i0;
            }
            if d1 && rows.1 != t.i1 {
                hpass_words(canvas_row(t.i1), &self.xt, lo, hi, &mut self.h1);
                rows.1 = t.i1;
            }
            let tmpl = |r: usize| &self.template_h[self.slot[r] * drow..(self.slot[r] + 1) * drow];
            let a = if d0 { &self.h0[..] } else { tmpl(t.i0) };
            let b = if d1 { &self.h1[..] } else { tmpl(t.i1) };
            vpass(&a[cl..ch], &b[cl..ch], t.w0, t.w1, &mut o[cl..ch]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::GOAL;

    fn scene(agent: [f64; 2], block: Pose) -> Scene {
        Scene {
            agent,
            block,
            goal: GOAL,
        }
    }

    #[test]
    fn light_colours_follow_gym_pusht() {
        let light =
            |c: [u8; 3]| c.map(|v| (1.2f32 * f32::from(v)).min(255.0).round_ties_even() as u8);
        assert_eq!(light(BLOCK_OUTLINE), BLOCK_FILL);
        assert_eq!(light(AGENT_OUTER), AGENT_INNER);
    }

    #[test]
    fn bad_sizes_and_buffers_are_errors() {
        let mut r = Renderer::new(GOAL);
        let s = scene(
            [100.0, 100.0],
            Pose {
                x: 300.0,
                y: 300.0,
                theta: 0.3,
            },
        );
        assert_eq!(
            r.observation(&s, 0, 96),
            Err(RenderError::InvalidSize {
                width: 0,
                height: 96,
                max: MAX_IMAGE_SIDE
            })
        );
        assert!(matches!(
            r.observation(&s, 96, MAX_IMAGE_SIDE + 1),
            Err(RenderError::InvalidSize { .. })
        ));
        let mut small = vec![0u8; 96 * 96 * 3 - 1];
        assert_eq!(
            r.observation_into(&s, 96, 96, &mut small),
            Err(RenderError::BufferLength {
                name: "out",
                expected: 96 * 96 * 3,
                actual: 96 * 96 * 3 - 1
            })
        );
        assert!(matches!(
            r.visualization(&s, None, 0, 0),
            Err(RenderError::InvalidSize { .. })
        ));
        let src = vec![0u8; 12];
        let mut dst = vec![0u8; 3];
        assert!(matches!(
            resize_bilinear_u8(&src, 2, 2, 3, &mut dst, 1, 1),
            Ok(())
        ));
        assert_eq!(
            resize_bilinear_u8(&src, 2, 2, 0, &mut dst, 1, 1),
            Err(RenderError::InvalidChannels {
                channels: 0,
                max: MAX_CHANNELS
            })
        );
        assert!(matches!(
            resize_bilinear_u8(&src, 3, 2, 3, &mut dst, 1, 1),
            Err(RenderError::BufferLength { name: "src", .. })
        ));
        assert!(matches!(
            resize_bilinear_u8(&src, 2, 2, 3, &mut dst, 2, 1),
            Err(RenderError::BufferLength { name: "dst", .. })
        ));
        assert!(matches!(
            resize_bilinear_u8(&src, 0, 2, 3, &mut dst, 1, 1),
            Err(RenderError::InvalidSize { .. })
        ));
    }

    #[test]
    fn block_on_goal_hides_all_green() {
        let mut r = Renderer::new(GOAL);
        let s = scene([60.0, 60.0], GOAL);
        let canvas = r.canvas_rgb(&s);
        assert!(!canvas.chunks_exact(3).any(|p| p == GOAL_GREEN));
        let obs = r.observation(&s, 96, 96).unwrap_or_default();
        assert!(!obs.chunks_exact(3).any(|p| p == GOAL_GREEN));
        // Elsewhere the goal shows.
        let away = scene(
            [60.0, 60.0],
            Pose {
                x: 120.0,
                y: 420.0,
                theta: 0.0,
            },
        );
        assert!(r.canvas_rgb(&away).chunks_exact(3).any(|p| p == GOAL_GREEN));
    }

    #[test]
    fn output_is_deterministic_and_independent_of_history() {
        let scenes = [
            scene(
                [100.0, 100.0],
                Pose {
                    x: 300.0,
                    y: 300.0,
                    theta: 0.3,
                },
            ),
            scene(
                [256.4, 300.6],
                Pose {
                    x: 256.0,
                    y: 300.0,
                    theta: -2.0,
                },
            ),
            scene(
                [20.0, 500.0],
                Pose {
                    x: 80.0,
                    y: 470.0,
                    theta: 1.0,
                },
            ),
        ];
        let mut warm = Renderer::new(GOAL);
        for s in &scenes {
            let mut fresh = Renderer::new(GOAL);
            let a = warm.observation(s, 96, 96).unwrap_or_default();
            let b = fresh.observation(s, 96, 96).unwrap_or_default();
            assert_eq!(a, b);
            let mut full = vec![0u8; 96 * 96 * 3];
            let canvas = fresh.canvas_rgb(s);
            assert!(resize_bilinear_u8(&canvas, 512, 512, 3, &mut full, 96, 96).is_ok());
            assert_eq!(a, full, "cached-row resize must equal the plain resize");
            assert_eq!(warm.canvas_rgb(s), canvas);
        }
    }

    #[test]
    fn a_scene_with_another_goal_redraws_the_template() {
        let other = Pose {
            x: 200.0,
            y: 300.0,
            theta: -0.5,
        };
        let mut s = scene(
            [100.0, 100.0],
            Pose {
                x: 300.0,
                y: 300.0,
                theta: 0.3,
            },
        );
        let mut r = Renderer::new(GOAL);
        let before = r.observation(&s, 96, 96).unwrap_or_default();
        s.goal = other;
        let after = r.observation(&s, 96, 96).unwrap_or_default();
        assert_ne!(before, after);
        assert_eq!(r.goal(), other);
        assert_eq!(
            after,
            Renderer::new(other)
                .observation(&s, 96, 96)
                .unwrap_or_default()
        );
        assert_eq!(r.canvas_rgb(&s), Renderer::new(other).canvas_rgb(&s));
    }

    #[test]
    fn non_finite_and_far_away_scenes_do_not_panic() {
        let mut r = Renderer::new(GOAL);
        for v in [f64::NAN, f64::INFINITY, -1e300, 1e9] {
            let s = scene(
                [v, v],
                Pose {
                    x: v,
                    y: -v,
                    theta: v,
                },
            );
            assert!(r.observation(&s, 84, 84).is_ok());
            assert!(r.visualization(&s, Some([v, v]), 100, 100).is_ok());
        }
    }

    #[test]
    fn marker_is_drawn_on_visualisation_only() {
        let mut r = Renderer::new(GOAL);
        let s = scene(
            [100.0, 100.0],
            Pose {
                x: 300.0,
                y: 300.0,
                theta: 0.3,
            },
        );
        let vis = r
            .visualization(&s, Some([256.0, 128.0]), 680, 680)
            .unwrap_or_default();
        let red = vis.chunks_exact(3).filter(|p| *p == MARKER_RED).count();
        // cv2 draws 1025 px for this marker (size 56, thickness 7) on a blank image.
        assert_eq!(red, 1025);
        let plain = r.visualization(&s, None, 680, 680).unwrap_or_default();
        assert!(!plain.chunks_exact(3).any(|p| p == MARKER_RED));
    }
}
