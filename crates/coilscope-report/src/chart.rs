//! Line charts drawn by plotters into SVG (inline in the report) and PNG (beside it).
//!
//! The font is DejaVu Sans, embedded in the binary (`fonts/`, with its licence) and registered
//! with plotters' ab_glyph text backend, so no system font or fontconfig is needed. A log
//! frequency axis is drawn as `log10(f)` with labels written back in Hz.

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};
use std::sync::Once;

static FONT: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");
static REGISTER: Once = Once::new();

fn ensure_font() {
    REGISTER.call_once(|| {
        // The embedded bytes are a valid TrueType font; a failure here is a build defect.
        if register_font("sans-serif", FontStyle::Normal, FONT).is_err() {
            eprintln!("coilscope-report: the embedded font did not load");
        }
    });
}

/// Colours of the series, in order.
pub const PALETTE: [RGBColor; 6] = [
    RGBColor(0x1f, 0x5f, 0xbf),
    RGBColor(0xd6, 0x27, 0x28),
    RGBColor(0x2c, 0xa0, 0x2c),
    RGBColor(0xff, 0x7f, 0x0e),
    RGBColor(0x94, 0x67, 0xbd),
    RGBColor(0x17, 0x17, 0x17),
];

/// One curve.
#[derive(Clone, Debug)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Draw as dashes (a prediction rather than the reference).
    pub dashed: bool,
}

/// A shaded band `lo..hi` around a curve (e.g. +-2 sd), drawn in the colour of series `of`.
#[derive(Clone, Debug)]
pub struct Band {
    pub of: usize,
    pub lo: Vec<(f64, f64)>,
    pub hi: Vec<(f64, f64)>,
}

/// A chart: title, axes, curves, bands and labelled vertical markers.
#[derive(Clone, Debug)]
pub struct Chart {
    /// File-name-safe id (PNG name, HTML anchor).
    pub id: String,
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub series: Vec<Series>,
    pub bands: Vec<Band>,
    /// Vertical lines at x with a label.
    pub markers: Vec<(f64, String)>,
    /// The lowest value the y axis shows (a decibel axis stops at what is measurable; the
    /// points below it are drawn on it).
    pub y_floor: Option<f64>,
}

impl Chart {
    pub fn new(id: &str, title: &str, x_label: &str, y_label: &str) -> Self {
        Chart {
            id: id.into(),
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            log_x: false,
            series: vec![],
            bands: vec![],
            markers: vec![],
            y_floor: None,
        }
    }
    pub fn log_x(mut self) -> Self {
        self.log_x = true;
        self
    }
    pub fn line(mut self, name: &str, points: Vec<(f64, f64)>) -> Self {
        self.series.push(Series { name: name.into(), points, dashed: false });
        self
    }
    pub fn dashed(mut self, name: &str, points: Vec<(f64, f64)>) -> Self {
        self.series.push(Series { name: name.into(), points, dashed: true });
        self
    }
    pub fn band(mut self, lo: Vec<(f64, f64)>, hi: Vec<(f64, f64)>) -> Self {
        let of = self.series.len().saturating_sub(1);
        self.bands.push(Band { of, lo, hi });
        self
    }
    /// Clip the y axis at `floor` (see [`Chart::y_floor`]).
    pub fn floor(mut self, floor: f64) -> Self {
        self.y_floor = Some(floor);
        self
    }
    pub fn marker(mut self, x: f64, label: &str) -> Self {
        self.markers.push((x, label.into()));
        self
    }

    fn tx(&self, x: f64) -> f64 {
        if self.log_x {
            x.max(1e-30).log10()
        } else {
            x
        }
    }

    /// Points with finite coordinates (and positive x on a log axis), axis-transformed.
    fn clean(&self, pts: &[(f64, f64)]) -> Vec<(f64, f64)> {
        let floor = self.y_floor.unwrap_or(f64::NEG_INFINITY);
        pts.iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite() && (!self.log_x || *x > 0.0))
            .map(|&(x, y)| (self.tx(x), y.max(floor)))
            .collect()
    }

    /// Whether a series or band has a point with finite coordinates ([`Chart::svg`] fails
    /// without one).
    pub fn has_finite_data(&self) -> bool {
        self.bounds().is_some()
    }

    fn bounds(&self) -> Option<((f64, f64), (f64, f64))> {
        let all: Vec<(f64, f64)> = self
            .series
            .iter()
            .flat_map(|s| self.clean(&s.points))
            .chain(self.bands.iter().flat_map(|b| self.clean(&b.lo).into_iter().chain(self.clean(&b.hi))))
            .collect();
        if all.is_empty() {
            return None;
        }
        let fold = |f: fn(&(f64, f64)) -> f64| {
            all.iter().map(f).fold((f64::INFINITY, f64::NEG_INFINITY), |a, v| (a.0.min(v), a.1.max(v)))
        };
        let (mut x, mut y) = (fold(|p| p.0), fold(|p| p.1));
        if x.1 - x.0 <= 0.0 {
            x = (x.0 - 0.5, x.1 + 0.5);
        }
        let pad = if y.1 > y.0 { 0.06 * (y.1 - y.0) } else { 0.5 * y.0.abs().max(1e-12) };
        // Room above the data for the legend (upper right): a line per series.
        let legend =
            if self.series.len() > 1 { 0.075 * self.series.len() as f64 * (y.1 - y.0 + 2.0 * pad) } else { 0.0 };
        y = (y.0 - pad, y.1 + pad + legend);
        Some((x, y))
    }

    /// Tick positions of the x axis: on a log axis the 1-2-5 values of each decade (in
    /// log10), so that labels read 20, 50, 100, 200, ... rather than 158, 251, 398; on a
    /// linear axis about ten round steps.
    fn x_keys(&self, x0: f64, x1: f64) -> Vec<f64> {
        if self.log_x {
            let mut keys = vec![];
            let steps: &[f64] = if x1 - x0 > 2.5 {
                &[1.0]
            } else if x1 - x0 > 1.2 {
                &[1.0, 2.0, 5.0]
            } else {
                &[1.0, 1.5, 2.0, 3.0, 5.0, 7.0]
            };
            for d in (x0.floor() as i32 - 1)..=(x1.ceil() as i32) {
                for m in steps {
                    let v = (m * 10f64.powi(d)).log10();
                    if v >= x0 && v <= x1 {
                        keys.push(v);
                    }
                }
            }
            keys
        } else {
            let span = x1 - x0;
            let raw = span / 10.0;
            let mag = 10f64.powf(raw.log10().floor());
            let step = [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| span / s <= 12.0).unwrap_or(10.0 * mag);
            let first = (x0 / step).ceil() as i64;
            let last = (x1 / step).floor() as i64;
            (first..=last).map(|k| k as f64 * step).collect()
        }
    }

    /// Draw on any plotters backend.
    pub fn draw<DB: DrawingBackend>(&self, root: DrawingArea<DB, plotters::coord::Shift>) -> Result<(), String> {
        self.draw_with(root, true)
    }

    /// Draw, with or without the legend (the legend test compares the two).
    fn draw_with<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, plotters::coord::Shift>,
        legend: bool,
    ) -> Result<(), String> {
        ensure_font();
        let e = |err: DrawingAreaErrorKind<DB::ErrorType>| format!("chart {}: {err}", self.id);
        root.fill(&WHITE).map_err(e)?;
        let ((x0, x1), (y0, y1)) = self.bounds().ok_or_else(|| format!("chart {}: no finite data to draw", self.id))?;
        let log = self.log_x;
        let mut chart = ChartBuilder::on(&root)
            .caption(&self.title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(e)?;
        let fmt_x = move |v: &f64| {
            if log {
                let f = 10f64.powf(*v);
                if f >= 1000.0 {
                    format!("{:.1}k", f / 1000.0).replace(".0k", "k")
                } else if f >= 10.0 {
                    format!("{f:.0}")
                } else if f >= 1.0 {
                    format!("{f:.1}")
                } else {
                    format!("{f:.2}")
                }
            } else {
                format!("{v:.3}").trim_end_matches('0').trim_end_matches('.').to_string()
            }
        };
        let fmt_y = |v: &f64| {
            let a = v.abs();
            if a != 0.0 && !(1e-2..1e4).contains(&a) {
                format!("{v:.2e}")
            } else {
                format!("{v:.3}").trim_end_matches('0').trim_end_matches('.').to_string()
            }
        };
        // The x ticks are ours (x_keys: 1-2-5 per decade on a log axis): the mesh draws the
        // y axis, and the x grid lines and labels are drawn below at the keys.
        chart
            .configure_mesh()
            .x_desc(&self.x_label)
            .y_desc(&self.y_label)
            .x_labels(0)
            .disable_x_mesh()
            .y_label_formatter(&fmt_y)
            .label_style(("sans-serif", 13))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()
            .map_err(e)?;
        let keys = self.x_keys(x0, x1);
        let grid = RGBColor(225, 225, 225);
        for &k in &keys {
            chart
                .draw_series(std::iter::once(PathElement::new(vec![(k, y0), (k, y1)], grid.stroke_width(1))))
                .map_err(e)?;
            let (px, py) = chart.backend_coord(&(k, y0));
            let text = fmt_x(&k);
            let w = 7 * text.chars().count() as i32 / 2;
            root.draw(&Text::new(text, (px - w, py + 6), ("sans-serif", 13).into_font().color(&BLACK))).map_err(e)?;
            root.draw(&PathElement::new(vec![(px, py), (px, py + 4)], BLACK.stroke_width(1))).map_err(e)?;
        }
        for b in &self.bands {
            let c = PALETTE[b.of % PALETTE.len()];
            let mut poly = self.clean(&b.lo);
            poly.extend(self.clean(&b.hi).into_iter().rev());
            chart.draw_series(std::iter::once(Polygon::new(poly, c.mix(0.22).filled()))).map_err(e)?;
        }
        let mut placed: Vec<(f64, f64)> = vec![];
        for (x, label) in &self.markers {
            let tx = self.tx(*x);
            if !(x0..=x1).contains(&tx) {
                continue;
            }
            // A label near one already placed goes a line lower, so that none covers another.
            let near = placed
                .iter()
                .filter(|(px, _)| (px - tx).abs() < 0.0125 * (x1 - x0) * label.chars().count().max(6) as f64)
                .count();
            placed.push((tx, 0.0));
            let grey = RGBColor(110, 110, 110);
            chart
                .draw_series(DashedLineSeries::new(vec![(tx, y0), (tx, y1)], 6, 4, grey.stroke_width(1)))
                .map_err(e)?;
            // Labels right of the middle are written to the left of their line, so they stay inside.
            let width = 0.0125 * (x1 - x0) * label.chars().count() as f64;
            let lx = if tx > 0.5 * (x0 + x1) { tx - width - 0.005 * (x1 - x0) } else { tx + 0.005 * (x1 - x0) };
            chart
                .draw_series(std::iter::once(Text::new(
                    label.clone(),
                    (lx, y1 - (0.04 + 0.05 * near as f64) * (y1 - y0)),
                    ("sans-serif", 12).into_font().color(&grey),
                )))
                .map_err(e)?;
        }
        for (k, s) in self.series.iter().enumerate() {
            let c = PALETTE[k % PALETTE.len()];
            let pts = self.clean(&s.points);
            let style = c.stroke_width(2);
            let anno = if s.dashed {
                chart.draw_series(DashedLineSeries::new(pts, 8, 5, style)).map_err(e)?
            } else {
                chart.draw_series(LineSeries::new(pts, style)).map_err(e)?
            };
            anno.label(s.name.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2)));
        }
        if legend && self.series.len() > 1 {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(200, 200, 200))
                .label_font(("sans-serif", 13))
                .position(SeriesLabelPosition::UpperRight)
                .draw()
                .map_err(e)?;
        }
        root.present().map_err(e)?;
        Ok(())
    }

    /// The chart as an SVG document.
    pub fn svg(&self, size: (u32, u32)) -> Result<String, String> {
        let mut out = String::new();
        self.draw(SVGBackend::with_string(&mut out, size).into_drawing_area())?;
        Ok(out)
    }

    /// The chart's pixels (RGB).
    fn rgb(&self, size: (u32, u32), legend: bool) -> Result<Rgb, String> {
        let mut px = vec![0u8; (size.0 * size.1 * 3) as usize];
        self.draw_with(BitMapBackend::with_buffer(&mut px, size).into_drawing_area(), legend)?;
        Ok(Rgb { width: size.0, height: size.1, px })
    }

    /// The layout check of the reports' charts: how many pixels of the data lines the legend box covers
    /// at `size` (0 for a good layout). The box is where the chart drawn with and without its
    /// legend differs; the data lines are the pixels of a series colour in the chart drawn
    /// without it.
    pub fn legend_covers_data(&self, size: (u32, u32)) -> Result<usize, String> {
        let (with, without) = (self.rgb(size, true)?, self.rgb(size, false)?);
        let diff: Vec<(u32, u32)> =
            with.pixels().filter(|&(x, y, p)| without.get(x, y) != p).map(|(x, y, _)| (x, y)).collect();
        let (Some(x0), Some(x1)) = (diff.iter().map(|p| p.0).min(), diff.iter().map(|p| p.0).max()) else {
            return Ok(0);
        };
        let (y0, y1) = (diff.iter().map(|p| p.1).min().unwrap_or(0), diff.iter().map(|p| p.1).max().unwrap_or(0));
        let colours: Vec<[u8; 3]> = (0..self.series.len()).map(|k| PALETTE[k % PALETTE.len()].rgb().into()).collect();
        Ok(without
            .pixels()
            .filter(|(x, y, p)| (x0..=x1).contains(x) && (y0..=y1).contains(y) && colours.contains(p))
            .count())
    }

    /// The chart as PNG bytes.
    pub fn png(&self, size: (u32, u32)) -> Result<Vec<u8>, String> {
        let img = self.rgb(size, true)?;
        let mut bytes = Vec::new();
        let mut enc = png::Encoder::new(&mut bytes, img.width, img.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header()
            .and_then(|mut w| w.write_image_data(&img.px))
            .map_err(|e| format!("chart {}: PNG encoding failed: {e}", self.id))?;
        Ok(bytes)
    }
}

/// An 8-bit RGB image, row by row: a chart's pixels, or a PNG read back by [`Rgb::from_png`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rgb {
    pub width: u32,
    pub height: u32,
    /// `3 * width * height` bytes, rows from the top.
    pub px: Vec<u8>,
}

impl Rgb {
    /// The pixel at column `x`, row `y`.
    pub fn get(&self, x: u32, y: u32) -> [u8; 3] {
        let k = 3 * (y as usize * self.width as usize + x as usize);
        [self.px[k], self.px[k + 1], self.px[k + 2]]
    }

    /// Every pixel with its column and row.
    pub fn pixels(&self) -> impl Iterator<Item = (u32, u32, [u8; 3])> + '_ {
        let w = self.width.max(1);
        self.px.chunks_exact(3).enumerate().map(move |(k, c)| (k as u32 % w, k as u32 / w, [c[0], c[1], c[2]]))
    }

    /// A PNG's first frame as 8-bit RGB (grey expanded, alpha dropped): what a report's PNG
    /// copy, or a browser's screenshot of the report, shows.
    pub fn from_png(bytes: &[u8]) -> Result<Rgb, String> {
        let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
        dec.set_transformations(png::Transformations::normalize_to_color8());
        let mut reader = dec.read_info().map_err(|e| format!("not a PNG: {e}"))?;
        let mut buf = vec![0u8; reader.output_buffer_size().ok_or("the PNG is too large to read")?];
        let info = reader.next_frame(&mut buf).map_err(|e| format!("PNG data: {e}"))?;
        let buf = &buf[..info.buffer_size()];
        let px: Vec<u8> = match info.color_type {
            png::ColorType::Rgb => buf.to_vec(),
            png::ColorType::Rgba => buf.chunks_exact(4).flat_map(|c| [c[0], c[1], c[2]]).collect(),
            png::ColorType::Grayscale => buf.iter().flat_map(|&g| [g, g, g]).collect(),
            png::ColorType::GrayscaleAlpha => buf.chunks_exact(2).flat_map(|c| [c[0], c[0], c[0]]).collect(),
            png::ColorType::Indexed => return Err("an indexed PNG was not expanded".into()),
        };
        Ok(Rgb { width: info.width, height: info.height, px })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Chart {
        Chart::new("t", "Test", "x (mm)", "Bl (T m)")
            .line("Bl", (0..50).map(|k| (k as f64 * 0.1, 5.0 - 0.01 * (k * k) as f64)).collect())
            .band(
                (0..50).map(|k| (k as f64 * 0.1, 4.9 - 0.01 * (k * k) as f64)).collect(),
                (0..50).map(|k| (k as f64 * 0.1, 5.1 - 0.01 * (k * k) as f64)).collect(),
            )
            .dashed("published", vec![(0.0, 5.0), (4.9, 0.0)])
            .marker(2.0, "x_max")
    }

    #[test]
    fn svg_has_the_curves_and_the_text() {
        let s = sample().svg((640, 400)).unwrap();
        assert!(s.starts_with("<svg") && s.contains("</svg>"));
        assert!(s.contains("Bl (T m)") && s.contains("x_max") && s.contains("published"));
        assert!(s.matches("<polyline").count() >= 2, "two data lines");
        assert!(s.contains("<polygon"), "the band");
    }

    #[test]
    fn png_draws_the_series_colour() {
        let bytes = sample().png((640, 400)).unwrap();
        let img = Rgb::from_png(&bytes).unwrap();
        assert_eq!((img.width, img.height), (640, 400));
        assert_eq!(img, sample().rgb((640, 400), true).unwrap(), "the PNG holds the chart's pixels");
        let blue = img.pixels().filter(|p| p.2 == [0x1f, 0x5f, 0xbf]).count();
        assert!(blue > 200, "the first series is drawn ({blue} pixels)");
    }

    #[test]
    fn a_chart_without_finite_data_is_an_error() {
        let c = Chart::new("empty", "E", "x", "y").line("nan", vec![(f64::NAN, 1.0)]);
        assert!(c.svg((200, 100)).unwrap_err().contains("no finite data"));
    }
}

#[cfg(test)]
mod axis_tests {
    use super::*;

    /// A log frequency axis is ticked at 1-2-5 per decade (labels 20, 50, 100, ...
    /// rather than 158, 251, 398), and a decibel axis stops at its floor.
    #[test]
    fn log_ticks_are_round_and_the_floor_clips() {
        let c = Chart::new("f", "F", "frequency (Hz)", "dB")
            .log_x()
            .line("a", vec![(20.0, -30.0), (5000.0, -200.0)])
            .floor(-100.0);
        let keys = c.x_keys(20f64.log10(), 5000f64.log10());
        let hz: Vec<f64> = keys.iter().map(|k| 10f64.powf(*k)).collect();
        for want in [20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 5000.0] {
            assert!(hz.iter().any(|h| (h / want - 1.0).abs() < 1e-9), "{want} Hz not a tick: {hz:?}");
        }
        assert!(
            hz.iter().all(|h| {
                let m = h / 10f64.powf(h.log10().floor());
                [1.0, 2.0, 5.0].iter().any(|r| (m - r).abs() < 1e-9)
            }),
            "{hz:?}"
        );
        let ((_, _), (y0, _)) = c.bounds().unwrap();
        assert!(y0 >= -100.0 - 0.1 * 70.0, "the axis goes below the floor: {y0}");
        let s = c.svg((640, 400)).unwrap();
        assert!(s.contains(">1k<") || s.contains(">1k </") || s.contains("1k"), "the 1 kHz label");
    }
}

#[cfg(test)]
mod legend_tests {
    use super::*;

    #[test]
    fn the_legend_check_catches_a_legend_over_data() {
        // The negative control: a line through the upper right corner, where the legend sits.
        let c = Chart::new("t", "T", "x", "y")
            .line("a", (0..=100).map(|k| (k as f64, if k > 60 { 10.0 } else { 0.0 })).collect())
            .line("b", vec![(0.0, 0.0), (100.0, 10.0)]);
        // Its room above the data is kept: a legend there covers nothing...
        assert_eq!(c.legend_covers_data((960, 560)).unwrap(), 0);
        // ... and one drawn with no room is caught.
        let mut tight = c.clone();
        tight.series.extend((0..6).map(|k| Series {
            name: format!("s{k}"),
            points: vec![(0.0, 0.0), (100.0, 10.0)],
            dashed: false,
        }));
        assert!(tight.legend_covers_data((960, 300)).unwrap() > 0);
    }
}
