//! Line plots of a report (plotters): the same drawing goes to SVG and to PNG.
//!
//! PNG text needs glyph outlines, so the bundled DejaVu Sans (Debian `fonts-dejavu-core`,
//! Bitstream Vera licence, see `assets/fonts/LICENSE-DejaVu.txt`) is registered with
//! plotters' `ab_glyph` backend as the `sans-serif` family before anything is drawn. The
//! PNG is rasterised into an RGB buffer and encoded with the `png` crate (no image crate).

use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

use super::ReportError;

/// DejaVu Sans 2.37 (Debian `fonts-dejavu-core`).
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// Font family every text of a plot uses.
const FAMILY: &str = "sans-serif";

/// Size of a plot in pixels (its plotting area, with the legend inside it).
pub(super) const SIZE: (u32, u32) = (720, 450);

/// Width added on the right for the legend of a plot with more than [`INSIDE_LEGEND`]
/// series, which would cover the data inside the plotting area.
const LEGEND_WIDTH: u32 = 300;

/// The most series whose legend is drawn inside the plotting area.
const INSIDE_LEGEND: usize = 4;

/// Line colours, in series order (Tableau 10).
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// One point of a series, with an optional symmetric error bar.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Point {
    pub x: f64,
    pub y: f64,
    pub err: Option<f64>,
}

/// One line of a plot.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Series {
    pub label: String,
    pub points: Vec<Point>,
}

/// Everything needed to draw one plot.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct PlotSpec {
    /// File stem (`plots/<name>.svg`).
    pub name: String,
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// The x axis counts something (q): labels are integers.
    pub integer_x: bool,
    /// The x axis is logarithmic (budgets spanning decades: PGD iterations, step sizes);
    /// every x must then be > 0.
    pub log_x: bool,
    /// A y range the axis always includes (e.g. `[0, 1]` for coverage).
    pub y_include: (f64, f64),
    /// A horizontal reference line (e.g. 0 and 1 for a recovered fraction).
    pub y_refs: Vec<f64>,
    pub series: Vec<Series>,
}

impl PlotSpec {
    /// Whether the legend goes in a panel right of the plotting area.
    fn legend_outside(&self) -> bool {
        self.series.len() > INSIDE_LEGEND
    }

    /// Size of the drawing in pixels: [`SIZE`], wider by the legend's panel where it has one.
    pub(super) fn size(&self) -> (u32, u32) {
        if self.legend_outside() {
            (SIZE.0 + LEGEND_WIDTH, SIZE.1)
        } else {
            SIZE
        }
    }

    /// The spec as drawn: on a logarithmic axis, every x replaced by its `log10` (the
    /// ticks print `10^x` back).
    fn drawn(&self) -> std::borrow::Cow<'_, Self> {
        if !self.log_x {
            return std::borrow::Cow::Borrowed(self);
        }
        let mut d = self.clone();
        for p in d.series.iter_mut().flat_map(|s| s.points.iter_mut()) {
            p.x = p.x.log10();
        }
        std::borrow::Cow::Owned(d)
    }

    fn points(&self) -> impl Iterator<Item = &Point> {
        self.series.iter().flat_map(|s| s.points.iter())
    }

    /// Axis ranges, never empty or non-finite.
    fn ranges(&self) -> ((f64, f64), (f64, f64)) {
        let (mut x0, mut x1) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut y0, mut y1) = self.y_include;
        for p in self.points() {
            let e = p.err.unwrap_or(0.0);
            x0 = x0.min(p.x);
            x1 = x1.max(p.x);
            y0 = y0.min(p.y - e);
            y1 = y1.max(p.y + e);
        }
        if !(x0.is_finite() && x1.is_finite()) {
            (x0, x1) = (0.0, 1.0);
        }
        let xpad = if x1 > x0 { 0.08 * (x1 - x0) } else { 0.5 };
        let (x0, x1) = if self.integer_x {
            (x0 - xpad.max(0.4), x1 + xpad.max(0.4))
        } else {
            (x0 - xpad, x1 + xpad)
        };
        if !(y0.is_finite() && y1.is_finite()) {
            (y0, y1) = (0.0, 1.0);
        }
        let ypad = if y1 > y0 { 0.05 * (y1 - y0) } else { 0.5 };
        ((x0, x1), (y0 - ypad, y1 + ypad))
    }
}

/// A drawn plot: the spec and its SVG text.
#[derive(Debug, Clone, PartialEq)]
pub struct Plot {
    /// File stem: the plot is written as `plots/<name>.svg` and `plots/<name>.png`.
    pub name: String,
    /// Caption.
    pub title: String,
    /// The plot as a standalone SVG document.
    pub svg: String,
    pub(super) spec: PlotSpec,
}

/// Registers the bundled font once.
fn ensure_font() -> Result<(), ReportError> {
    static OK: OnceLock<bool> = OnceLock::new();
    if *OK.get_or_init(|| register_font(FAMILY, FontStyle::Normal, FONT).is_ok()) {
        Ok(())
    } else {
        Err(ReportError::Font)
    }
}

fn plot_error(name: &str, reason: impl ToString) -> ReportError {
    ReportError::Plot {
        plot: name.to_string(),
        reason: reason.to_string(),
    }
}

impl Plot {
    /// Draws the SVG of `spec`.
    pub(super) fn new(spec: PlotSpec) -> Result<Self, ReportError> {
        ensure_font()?;
        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, spec.size()).into_drawing_area();
            draw(&root, &spec).map_err(|e| plot_error(&spec.name, e))?;
        }
        Ok(Self {
            name: spec.name.clone(),
            title: spec.title.clone(),
            svg,
            spec,
        })
    }

    /// Rasterises the plot and encodes it as PNG.
    pub fn png(&self) -> Result<Vec<u8>, ReportError> {
        ensure_font()?;
        let (w, h) = self.spec.size();
        let mut rgb = vec![0u8; w as usize * h as usize * 3];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
            draw(&root, &self.spec).map_err(|e| plot_error(&self.name, e))?;
        }
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, w, h);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut writer = enc.write_header().map_err(|e| plot_error(&self.name, e))?;
            writer
                .write_image_data(&rgb)
                .map_err(|e| plot_error(&self.name, e))?;
            writer.finish().map_err(|e| plot_error(&self.name, e))?;
        }
        Ok(out)
    }
}

/// Formats a label of a logarithmic axis at drawn position `v` (`log10` of the value):
/// the value with two significant digits, in exponent form below 0.01.
fn log_tick(v: f64) -> String {
    let x = 10f64.powf(v);
    if !(x.is_finite() && x > 0.0) {
        String::new()
    } else if x < 0.01 {
        let e = format!("{x:.1e}");
        let (m, exp) = e.split_once('e').unwrap_or((e.as_str(), "0"));
        format!("{}e{exp}", m.trim_end_matches('0').trim_end_matches('.'))
    } else if x < 10.0 {
        tick(x, false)
    } else {
        format!("{x:.0}")
    }
}

/// Formats an axis label: integers for counting axes, else a short decimal.
fn tick(v: f64, integer: bool) -> String {
    if integer {
        if (v - v.round()).abs() < 1e-9 {
            format!("{}", v.round() as i64)
        } else {
            String::new()
        }
    } else {
        let s = format!("{v:.2}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        if s == "-0" { "0".into() } else { s.into() }
    }
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    spec: &PlotSpec,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let (area, panel) = if spec.legend_outside() {
        let (a, p) = root.split_horizontally(SIZE.0);
        (a, Some(p))
    } else {
        (root.clone(), None)
    };
    if let Some(panel) = &panel {
        draw_legend(panel, spec)?;
    }
    let root = &area;
    let log = spec.log_x;
    let spec = &*spec.drawn();
    let ((x0, x1), (y0, y1)) = spec.ranges();
    let mut chart = ChartBuilder::on(root)
        .caption(&spec.title, (FAMILY, 20))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(60)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    let integer = spec.integer_x;
    let x_fmt = move |v: &f64| if log { log_tick(*v) } else { tick(*v, integer) };
    let y_fmt = |v: &f64| tick(*v, false);
    chart
        .configure_mesh()
        .x_desc(spec.x_label.as_str())
        .y_desc(spec.y_label.as_str())
        .x_labels(if integer {
            ((x1 - x0).round() as usize + 1).clamp(2, 12)
        } else {
            8
        })
        .y_labels(8)
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&y_fmt)
        .label_style((FAMILY, 13))
        .axis_desc_style((FAMILY, 15))
        .light_line_style(WHITE.mix(0.0))
        .draw()?;
    for &r in &spec.y_refs {
        if r > y0 && r < y1 {
            chart.draw_series(std::iter::once(PathElement::new(
                vec![(x0, r), (x1, r)],
                BLACK.mix(0.35).stroke_width(1),
            )))?;
        }
    }
    for (i, s) in spec.series.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(
                s.points.iter().map(|p| (p.x, p.y)),
                color.stroke_width(2),
            ))?
            .label(s.label.as_str())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
        chart.draw_series(s.points.iter().filter_map(|p| {
            p.err.map(|e| {
                ErrorBar::new_vertical(p.x, p.y - e, p.y, p.y + e, color.stroke_width(1), 8)
            })
        }))?;
        chart.draw_series(
            s.points
                .iter()
                .map(|p| Circle::new((p.x, p.y), 3, color.filled())),
        )?;
    }
    if !spec.series.is_empty() && panel.is_none() {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerLeft)
            .label_font((FAMILY, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .draw()?;
    }
    root.present()?;
    Ok(())
}

/// The legend in its own panel: one row per series, its colour's line and its label.
fn draw_legend<DB: DrawingBackend>(
    panel: &DrawingArea<DB, Shift>,
    spec: &PlotSpec,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (top, row) = (48, 22);
    for (i, s) in spec.series.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        let y = top + row * i as i32;
        panel.draw(&PathElement::new(
            vec![(8, y), (30, y)],
            color.stroke_width(2),
        ))?;
        panel.draw(&Circle::new((19, y), 3, color.filled()))?;
        panel.draw(&Text::new(
            s.label.clone(),
            (38, y - 7),
            (FAMILY, 13).into_font(),
        ))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_short_and_integer_axes_skip_fractions() {
        assert_eq!(tick(2.0, true), "2");
        assert_eq!(tick(2.5, true), "");
        assert_eq!(tick(0.25, false), "0.25");
        assert_eq!(tick(1.0, false), "1");
        assert_eq!(tick(-0.001, false), "0");
        assert_eq!(log_tick(-4.0), "1e-4");
        assert_eq!(log_tick(5e-4f64.log10()), "5e-4");
        assert_eq!(log_tick(1.5e-3f64.log10()), "1.5e-3");
        assert_eq!(log_tick(0.5f64.log10()), "0.5");
        assert_eq!(log_tick(1.0), "10");
        assert_eq!(log_tick(200f64.log10()), "200");
    }

    #[test]
    fn a_logarithmic_axis_draws_log10_of_x() {
        let spec = PlotSpec {
            name: "x".into(),
            title: "t".into(),
            x_label: "step".into(),
            y_label: "y".into(),
            integer_x: false,
            log_x: true,
            y_include: (0.0, 1.0),
            y_refs: vec![],
            series: vec![Series {
                label: "a".into(),
                points: [1e-4, 1e-2]
                    .map(|x| Point {
                        x,
                        y: 0.5,
                        err: None,
                    })
                    .to_vec(),
            }],
        };
        let xs: Vec<f64> = spec.drawn().points().map(|p| p.x).collect();
        assert!(
            (xs[0] + 4.0).abs() < 1e-12 && (xs[1] + 2.0).abs() < 1e-12,
            "{xs:?}"
        );
        let ((x0, x1), _) = spec.drawn().ranges();
        assert!(x0 < -4.0 && -2.0 < x1 && x1 < 0.0, "{x0} {x1}");
        assert!(Plot::new(spec.clone()).is_ok_and(|p| p.svg.contains("1e-4")));
        // Five series: the legend moves to a panel on the right, every label drawn once.
        let many = PlotSpec {
            series: (0..5)
                .map(|i| Series {
                    label: format!("series-{i}"),
                    ..spec.series[0].clone()
                })
                .collect(),
            ..spec
        };
        assert_eq!(many.size(), (SIZE.0 + LEGEND_WIDTH, SIZE.1));
        let p = Plot::new(many).expect("plot");
        assert!(
            p.svg
                .contains(&format!("width=\"{}\"", SIZE.0 + LEGEND_WIDTH))
        );
        for i in 0..5 {
            let n = p.svg.matches(&format!("series-{i}")).count();
            assert_eq!(n, 1, "series-{i} drawn once, in the panel");
        }
        let png = p.png().expect("png");
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    }

    #[test]
    fn ranges_are_never_empty() {
        let spec = PlotSpec {
            name: "x".into(),
            title: "t".into(),
            x_label: "q".into(),
            y_label: "y".into(),
            integer_x: true,
            log_x: false,
            y_include: (0.0, 0.0),
            y_refs: vec![],
            series: vec![Series {
                label: "a".into(),
                points: vec![Point {
                    x: 1.0,
                    y: 0.5,
                    err: None,
                }],
            }],
        };
        let ((x0, x1), (y0, y1)) = spec.ranges();
        assert!(x0 < 1.0 && 1.0 < x1 && y0 < 0.5 && 0.5 < y1);
        let empty = PlotSpec {
            series: vec![],
            ..spec
        };
        let ((x0, x1), (y0, y1)) = empty.ranges();
        assert!(x0 < x1 && y0 < y1);
    }
}
