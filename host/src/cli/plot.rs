//! Plots of an NPF model's D, F and G per channel (plotters, bitmap backend,
//! the DejaVu Sans font embedded so no system font library is needed).

use std::path::Path;
use std::sync::Once;

use plotters::prelude::*;

use crate::brdf::BINS;
use crate::brdf::coords::{cell_centre, g_bin_centre};
use crate::brdf::npf::NpfModel;

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // Cannot fail: the embedded font is a valid TrueType file.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// Why a plot could not be made.
#[derive(Debug, thiserror::Error)]
#[error("cannot draw the plot: {0}")]
pub struct PlotError(String);

/// A line of text to draw onto a picture: its words, the centre of its
/// left edge (`centred`: of the text itself) in px, and its height in px.
pub struct Caption {
    pub text: String,
    pub at: (i32, i32),
    pub centred: bool,
    pub size: f64,
}

/// Draw `captions` in light grey (DejaVu Sans) onto `img`, over what is
/// there.
pub fn draw_captions(img: &mut image::RgbImage, captions: &[Caption]) -> Result<(), PlotError> {
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    register_font();
    let (w, h) = img.dimensions();
    let root = BitMapBackend::with_buffer(img.as_mut(), (w, h)).into_drawing_area();
    for c in captions {
        let anchor = if c.centred { HPos::Center } else { HPos::Left };
        let style = ("sans-serif", c.size)
            .into_font()
            .color(&RGBColor(225, 225, 225))
            .pos(Pos::new(anchor, VPos::Center));
        root.draw(&Text::new(c.text.as_str(), c.at, style))
            .map_err(|e| PlotError(e.to_string()))?;
    }
    root.present().map_err(|e| PlotError(e.to_string()))
}

/// Draw a piece's outline onto `img`: the closed path `outline` through
/// its `corners` (px of `img`; straight sides, or curved by a lens) in red,
/// each corner marked and labelled with its uv, and an arrow along u from
/// (0, 0).
pub fn draw_outline(
    img: &mut image::RgbImage,
    corners: [[f64; 2]; 4],
    outline: &[[f64; 2]],
) -> Result<(), PlotError> {
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    register_font();
    let (w, h) = img.dimensions();
    let root = BitMapBackend::with_buffer(img.as_mut(), (w, h)).into_drawing_area();
    let at = |p: [f64; 2]| (p[0].round() as i32, p[1].round() as i32);
    let (red, green) = (RGBColor(255, 40, 40), RGBColor(40, 220, 40));
    let e = |e: DrawingAreaErrorKind<_>| PlotError(e.to_string());
    // A label centred at `p` on a dark box, legible over any texture.
    let label = |text: &str, p: (i32, i32), colour: RGBColor| -> Result<(), PlotError> {
        let style = ("sans-serif", 18.0)
            .into_font()
            .color(&colour)
            .pos(Pos::new(HPos::Center, VPos::Center));
        let (tw, th) = root.estimate_text_size(text, &style).map_err(e)?;
        let (hw, hh) = (tw as i32 / 2 + 4, th as i32 / 2 + 2);
        let back =
            Rectangle::new([(p.0 - hw, p.1 - hh), (p.0 + hw, p.1 + hh)], BLACK.mix(0.8).filled());
        root.draw(&back).map_err(e)?;
        root.draw(&Text::new(text.to_string(), p, style)).map_err(e)
    };
    let mut outline: Vec<(i32, i32)> = outline.iter().map(|&c| at(c)).collect();
    outline.extend(outline.first().copied());
    root.draw(&PathElement::new(outline, red.stroke_width(2))).map_err(e)?;
    let centre = [
        0.25 * corners.iter().map(|c| c[0]).sum::<f64>(),
        0.25 * corners.iter().map(|c| c[1]).sum::<f64>(),
    ];
    let inwards = |c: [f64; 2], by: f64| {
        let (dx, dy) = (centre[0] - c[0], centre[1] - c[1]);
        let len = dx.hypot(dy).max(1.0);
        [c[0] + by * dx / len, c[1] + by * dy / len]
    };
    for (k, (c, text)) in corners.iter().zip(["(0, 0)", "(1, 0)", "(1, 1)", "(0, 1)"]).enumerate() {
        let colour = if k == 0 { green } else { red };
        root.draw(&Circle::new(at(*c), 5, colour.stroke_width(2))).map_err(e)?;
        // Inside the piece, off its corner.
        label(text, at(inwards(*c, 30.0)), colour)?;
    }
    // u: a third of the way from (0, 0) towards (1, 0), inside the piece.
    let [a, b] = [corners[0], corners[1]];
    let start = inwards(a, 55.0);
    let end = [start[0] + (b[0] - a[0]) / 3.0, start[1] + (b[1] - a[1]) / 3.0];
    root.draw(&PathElement::new(vec![at(start), at(end)], green.stroke_width(3))).map_err(e)?;
    label("u", at(end), green)?;
    root.present().map_err(|e| PlotError(e.to_string()))
}

/// Plot D (log scale, over θh), F (over θd) and G (over θ) for R, G, B into a
/// PNG at `path` (written atomically).
pub fn plot_factors(model: &NpfModel, path: &Path) -> Result<(), PlotError> {
    register_font();
    let (w, h) = (1500u32, 500u32);
    let mut pixels = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| PlotError(e.to_string()))?;
        let panels = root.split_evenly((1, 3));
        let colors = [RGBColor(200, 30, 30), RGBColor(30, 150, 30), RGBColor(30, 60, 200)];
        let deg = |r: f64| r.to_degrees();
        let th: Vec<f64> = (0..BINS).map(|k| deg(cell_centre(k, 0, 0).theta_h)).collect();
        let td: Vec<f64> = (0..BINS).map(|k| deg(cell_centre(0, k, 0).theta_d)).collect();
        let tg: Vec<f64> = (0..BINS).map(|k| deg(g_bin_centre(k))).collect();
        type Pick = fn(&crate::brdf::npf::Channel) -> &[f64; BINS];
        let specs: [(&str, &str, &Vec<f64>, Pick, bool); 3] = [
            ("D(θh)", "θh (degrees)", &th, |c| &c.d, true),
            ("F(θd)", "θd (degrees)", &td, |c| &c.f, false),
            ("G(θ)", "θ (degrees)", &tg, |c| &c.g, false),
        ];
        for (panel, (title, xlabel, xs, pick, log)) in panels.iter().zip(specs) {
            let err = |e: &dyn std::fmt::Display| PlotError(e.to_string());
            let mut chart = ChartBuilder::on(panel)
                .caption(title, ("sans-serif", 24))
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(60)
                .build_cartesian_2d(0f64..90f64, if log { -6f64..0.05 } else { 0f64..1.05 })
                .map_err(|e| err(&e))?;
            chart
                .configure_mesh()
                .x_desc(xlabel)
                .y_desc(if log { "log10 value" } else { "value" })
                .draw()
                .map_err(|e| err(&e))?;
            for (c, color) in colors.iter().enumerate() {
                let table = pick(&model.channels[c]);
                let series = xs
                    .iter()
                    .zip(table.iter())
                    .map(|(x, v)| (*x, if log { v.max(1e-6).log10() } else { *v }));
                chart
                    .draw_series(LineSeries::new(series, color.stroke_width(2)))
                    .map_err(|e| err(&e))?
                    .label(["R", "G", "B"][c])
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
            }
            chart
                .configure_series_labels()
                .border_style(BLACK)
                .background_style(WHITE.mix(0.8))
                .draw()
                .map_err(|e| err(&e))?;
        }
        root.present().map_err(|e| PlotError(e.to_string()))?;
    }
    let img =
        image::RgbImage::from_raw(w, h, pixels).ok_or_else(|| PlotError("buffer size".into()))?;
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| PlotError(e.to_string()))?;
    crate::fsutil::write_atomic(path, &bytes).map_err(|e| PlotError(e.to_string()))
}
