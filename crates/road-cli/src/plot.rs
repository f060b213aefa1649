//! PNG figures without fonts (no system font libraries needed): scenes and loss curves.

use std::path::Path;

use anyhow::{Context, Result};
use plotters::prelude::*;

/// Paper style: map light grey, logged trajectories grey, predictions orange, history blue.
pub const MAP: RGBColor = RGBColor(215, 215, 215);
pub const LOGGED: RGBColor = RGBColor(110, 110, 110);
pub const PREDICTED: RGBColor = RGBColor(240, 140, 20);
pub const HISTORY: RGBColor = RGBColor(40, 90, 200);
/// The adversarial agent of the reactivity test.
pub const ADVERSARY: RGBColor = RGBColor(210, 30, 30);
/// An externally driven ego.
pub const EGO: RGBColor = RGBColor(30, 150, 70);

/// A polyline in metres with its colour and width.
#[derive(Debug, Clone)]
pub struct Stroke {
    pub points: Vec<(f64, f64)>,
    pub color: RGBColor,
    pub width: u32,
}

/// An agent's footprint: its four corners in metres, outlined in `color`, filled with `fill`.
#[derive(Debug, Clone)]
pub struct Footprint {
    pub corners: [[f64; 2]; 4],
    pub color: RGBColor,
    pub fill: Option<RGBColor>,
}

/// A ring around a point in metres (collisions are circled).
#[derive(Debug, Clone)]
pub struct Ring {
    pub centre: (f64, f64),
    pub radius_m: f64,
    pub color: RGBColor,
}

/// The square of metres a figure shows: `half_extent_m` around `centre`, `size_px` wide.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    pub size_px: u32,
    pub centre: (f64, f64),
    pub half_extent_m: f64,
}

impl View {
    /// The smallest square around `points` with `margin_m` to spare on every side.
    pub fn fit(points: impl IntoIterator<Item = (f64, f64)>, margin_m: f64, size_px: u32) -> Self {
        let (mut lo, mut hi) = (
            (f64::INFINITY, f64::INFINITY),
            (f64::NEG_INFINITY, f64::NEG_INFINITY),
        );
        for (x, y) in points {
            if x.is_finite() && y.is_finite() {
                lo = (lo.0.min(x), lo.1.min(y));
                hi = (hi.0.max(x), hi.1.max(y));
            }
        }
        if lo.0 > hi.0 {
            // Nothing to fit: a square around the origin.
            (lo, hi) = ((0.0, 0.0), (0.0, 0.0));
        }
        Self {
            size_px,
            centre: (0.5 * (lo.0 + hi.0), 0.5 * (lo.1 + hi.1)),
            half_extent_m: 0.5 * (hi.0 - lo.0).max(hi.1 - lo.1) + margin_m.max(1.0),
        }
    }

    fn scale(&self) -> f64 {
        f64::from(self.size_px) / (2.0 * self.half_extent_m)
    }

    /// Pixel coordinates of a point in metres (y up in metres, down in pixels).
    fn pixel(&self, (x, y): (f64, f64)) -> (i32, i32) {
        let scale = self.scale();
        (
            ((x - self.centre.0 + self.half_extent_m) * scale) as i32,
            ((self.centre.1 + self.half_extent_m - y) * scale) as i32,
        )
    }
}

/// Draws strokes (and dots at each stroke's end) fitted into a square PNG.
pub fn scene_png(
    path: &Path,
    strokes: &[Stroke],
    size_px: u32,
    centre: (f64, f64),
    half_extent_m: f64,
) -> Result<()> {
    figure_png(path, strokes, &[], &[], size_px, centre, half_extent_m)
}

/// Strokes, then footprints (outlined), then rings, in a square PNG around `centre`.
pub fn figure_png(
    path: &Path,
    strokes: &[Stroke],
    footprints: &[Footprint],
    rings: &[Ring],
    size_px: u32,
    centre: (f64, f64),
    half_extent_m: f64,
) -> Result<()> {
    let view = View {
        size_px,
        centre,
        half_extent_m,
    };
    let root = BitMapBackend::new(path, (size_px, size_px)).into_drawing_area();
    root.fill(&WHITE)?;
    draw(&root, &view, strokes, footprints, rings)?;
    root.present()
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// Draws strokes, footprints and rings over an RGB buffer of `view.size_px`² pixels as it
/// is (the animation draws its lanes once and each frame over a copy).
pub fn draw_rgb(
    rgb: &mut [u8],
    view: &View,
    strokes: &[Stroke],
    footprints: &[Footprint],
    rings: &[Ring],
) -> Result<()> {
    let root = BitMapBackend::with_buffer(rgb, (view.size_px, view.size_px)).into_drawing_area();
    draw(&root, view, strokes, footprints, rings)?;
    root.present()?;
    Ok(())
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    view: &View,
    strokes: &[Stroke],
    footprints: &[Footprint],
    rings: &[Ring],
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    for s in strokes {
        let pts: Vec<(i32, i32)> = s.points.iter().map(|&p| view.pixel(p)).collect();
        root.draw(&PathElement::new(
            pts.clone(),
            s.color.stroke_width(s.width),
        ))?;
        if s.color != MAP {
            if let Some(&last) = pts.last() {
                root.draw(&Circle::new(last, s.width as i32 + 1, s.color.filled()))?;
            }
        }
    }
    for f in footprints {
        let mut pts: Vec<(i32, i32)> = f.corners.iter().map(|c| view.pixel((c[0], c[1]))).collect();
        if let Some(fill) = f.fill {
            root.draw(&Polygon::new(pts.clone(), fill.filled()))?;
        }
        pts.push(pts[0]);
        root.draw(&PathElement::new(pts, f.color.stroke_width(2)))?;
    }
    for r in rings {
        let radius = (r.radius_m * view.scale()).max(4.0) as i32;
        root.draw(&Circle::new(
            view.pixel(r.centre),
            radius,
            r.color.stroke_width(3),
        ))?;
    }
    Ok(())
}

/// The window's map polylines (normalised) as wide light-grey strokes in metres.
pub fn window_map_strokes(window: &road_data::SceneWindow) -> Vec<Stroke> {
    let q = window.polyline_points;
    (0..window.polyline_count())
        .map(|p| Stroke {
            points: (0..q)
                .map(|k| {
                    let i = 2 * (p * q + k);
                    let m = window
                        .frame
                        .to_metres([window.polylines[i], window.polylines[i + 1]]);
                    (m[0], m[1])
                })
                .collect(),
            color: MAP,
            width: 6,
        })
        .collect()
}

/// A window state (normalised x, y, heading) as a plot point in metres.
pub fn window_point_m(window: &road_data::SceneWindow, state: [f32; 3]) -> (f64, f64) {
    let m = window.frame.to_metres([state[0], state[1]]);
    (m[0], m[1])
}

/// Every agent's logged path over `steps` of the window, one stroke each.
pub fn window_path_strokes(
    window: &road_data::SceneWindow,
    steps: std::ops::Range<usize>,
    color: RGBColor,
    width: u32,
) -> Vec<Stroke> {
    (0..window.agents)
        .map(|a| Stroke {
            points: steps
                .clone()
                .filter_map(|t| window.state(a, t))
                .map(|s| window_point_m(window, s))
                .collect(),
            color,
            width,
        })
        .collect()
}

/// A lanelet map's lane bounds as thin light-grey strokes.
pub fn lanelet_strokes(map: &road_data::LaneletMap) -> Vec<Stroke> {
    map.lanelets
        .iter()
        .flat_map(|l| [&l.left_m, &l.right_m])
        .map(|bound| Stroke {
            points: bound.iter().map(|p| (p[0], p[1])).collect(),
            color: MAP,
            width: 2,
        })
        .collect()
}

/// Training and validation loss (log scale) against steps.
pub fn loss_png(path: &Path, train: &[(f64, f64)], validation: &[(f64, f64)]) -> Result<()> {
    let (w, h) = (800u32, 450u32);
    let root = BitMapBackend::new(path, (w, h)).into_drawing_area();
    root.fill(&WHITE)?;
    let all: Vec<&(f64, f64)> = train
        .iter()
        .chain(validation)
        .filter(|p| p.1 > 0.0)
        .collect();
    if all.is_empty() {
        root.present()?;
        return Ok(());
    }
    let max_step = all.iter().map(|p| p.0).fold(1.0, f64::max);
    let (lo, hi) = all
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.1.ln()), hi.max(p.1.ln()))
        });
    let span = (hi - lo).max(1e-6);
    let margin = 20.0;
    let to_px = |(s, l): (f64, f64)| -> (i32, i32) {
        let x = margin + (s / max_step) * (f64::from(w) - 2.0 * margin);
        let y = margin + (hi - l.ln()) / span * (f64::from(h) - 2.0 * margin);
        (x as i32, y as i32)
    };
    root.draw(&PathElement::new(
        vec![
            to_px((0.0, hi.exp())),
            to_px((0.0, lo.exp())),
            to_px((max_step, lo.exp())),
        ],
        BLACK.stroke_width(1),
    ))?;
    // A running mean keeps the noisy per-step loss readable.
    let window = (train.len() / 100).max(1);
    let smoothed: Vec<(i32, i32)> = train
        .windows(window)
        .step_by(window.max(1))
        .map(|c| {
            to_px((
                c[c.len() - 1].0,
                c.iter().map(|p| p.1).sum::<f64>() / c.len() as f64,
            ))
        })
        .collect();
    root.draw(&PathElement::new(smoothed, HISTORY.stroke_width(2)))?;
    let val: Vec<(i32, i32)> = validation
        .iter()
        .filter(|p| p.1 > 0.0)
        .map(|&p| to_px(p))
        .collect();
    root.draw(&PathElement::new(val.clone(), PREDICTED.stroke_width(2)))?;
    for p in val {
        root.draw(&Circle::new(p, 3, PREDICTED.filled()))?;
    }
    root.present()
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// (step, value) points of a curve.
pub type Series = Vec<(f64, f64)>;

/// Reads `train_log.csv` into (step, loss) and (step, validation loss) series.
pub fn read_train_log(path: &Path) -> Result<(Series, Series)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let (mut train, mut val) = (Vec::new(), Vec::new());
    for (i, line) in text.lines().enumerate().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        anyhow::ensure!(f.len() == 7, "bad line ({}:{})", path.display(), i + 1);
        let step: f64 = f[0]
            .parse()
            .with_context(|| format!("bad step ({}:{})", path.display(), i + 1))?;
        if let Ok(loss) = f[1].parse::<f64>() {
            train.push((step, loss));
        }
        if let Ok(v) = f[5].parse::<f64>() {
            val.push((step, v));
        }
    }
    Ok((train, val))
}
