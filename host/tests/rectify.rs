//! `host::build::rectify`: a photograph taken in perspective of a piece
//! whose pattern is known analytically, rectified back onto the piece.

use host::build::linalg::Homography;
use host::build::rectify::{RectifyOptions, rectify};
use host::camera::Frame;

/// The piece's radiance at (x, y) mm: waves of 1.6–7 mm periods, in
/// [0.05, 0.95].
fn pattern(x: f64, y: f64) -> [f64; 3] {
    let a = (x * 1.1).sin() * (y * 0.9).cos();
    let b = (x * 2.3 + y * 3.1).sin();
    let c = (y * 3.9).cos();
    [0.5 + 0.3 * a + 0.15 * b, 0.5 + 0.45 * b, 0.5 + 0.2 * c + 0.25 * a]
        .map(|v| v.clamp(0.05, 0.95))
}

const HOLDER: f32 = 10.0;
const SIZE_MM: [f64; 2] = [40.0, 24.0];

/// A `w × h` px photograph of the piece seen through `h_uv` (piece uv →
/// photograph px), each pixel the mean of 6 × 6 points; the holder around
/// the piece is far brighter than it.
fn photograph(w: u32, ht: u32, h_uv: &Homography) -> Frame {
    let inv = h_uv.inverse().unwrap();
    let mut rgb = Vec::with_capacity((w * ht * 3) as usize);
    for y in 0..ht {
        for x in 0..w {
            let mut acc = [0.0f64; 3];
            for a in 0..6 {
                for b in 0..6 {
                    let p = [x as f64 + (a as f64 + 0.5) / 6.0, y as f64 + (b as f64 + 0.5) / 6.0];
                    let uv = inv.apply(p);
                    let v = if uv.iter().all(|u| (0.0..1.0).contains(u)) {
                        pattern(uv[0] * SIZE_MM[0], uv[1] * SIZE_MM[1])
                    } else {
                        [HOLDER as f64; 3]
                    };
                    for c in 0..3 {
                        acc[c] += v[c] / 36.0;
                    }
                }
            }
            rgb.extend(acc.map(|v| v as f32));
        }
    }
    Frame { width: w, height: ht, rgb }
}

const CORNERS: [[f64; 2]; 4] = [[100.0, 60.0], [560.0, 95.0], [515.0, 420.0], [130.0, 385.0]];

#[test]
fn a_perspective_photograph_is_rectified_onto_the_piece() {
    let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    let h = Homography::fit(&square, &CORNERS).unwrap();
    let photo = photograph(640, 480, &h);
    let opts = RectifyOptions { corners: CORNERS, size_mm: SIZE_MM, px_per_mm: Some(4.0) };
    let (out, report) = rectify(&photo, &opts).unwrap();
    assert_eq!((out.width, out.height), (160, 96));
    assert!(report.supersampling >= 3, "{report:?}");
    // Against the pattern's mean over each output pixel (8 × 8 points).
    let (mut se, mut n, mut worst_edge) = (0.0f64, 0usize, 0.0f32);
    for r in 0..96usize {
        for c in 0..160usize {
            let mut want = [0.0f64; 3];
            for a in 0..8 {
                for b in 0..8 {
                    let v = pattern(
                        (c as f64 + (a as f64 + 0.5) / 8.0) * 0.25,
                        (r as f64 + (b as f64 + 0.5) / 8.0) * 0.25,
                    );
                    for k in 0..3 {
                        want[k] += v[k] / 64.0;
                    }
                }
            }
            let got = &out.rgb[3 * (r * 160 + c)..][..3];
            let border = r == 0 || c == 0 || r == 95 || c == 159;
            for k in 0..3 {
                if border {
                    worst_edge = worst_edge.max(got[k]);
                } else {
                    se += (got[k] as f64 - want[k]).powi(2);
                    n += 1;
                }
            }
        }
    }
    // Measured 64.3 dB (peak 1).
    let psnr = 10.0 * (1.0 / (se / n as f64)).log10();
    assert!(psnr >= 55.0, "{psnr:.2} dB");
    // Nothing of the holder (10× brighter) reaches the border pixels.
    assert!(worst_edge < 1.0, "{worst_edge}");

    // By default the density is the photograph's least on the piece: the
    // left edge's 285 px over 24 mm at its shortest…
    let opts = RectifyOptions { px_per_mm: None, ..opts };
    let (out, report) = rectify(&photo, &opts).unwrap();
    let edge = |a: [f64; 2], b: [f64; 2], mm: f64| (a[0] - b[0]).hypot(a[1] - b[1]) / mm;
    let shortest = [
        edge(CORNERS[0], CORNERS[1], 40.0),
        edge(CORNERS[3], CORNERS[2], 40.0),
        edge(CORNERS[0], CORNERS[3], 24.0),
        edge(CORNERS[1], CORNERS[2], 24.0),
    ]
    .into_iter()
    .fold(f64::INFINITY, f64::min);
    assert!(report.px_per_mm <= shortest * 1.001, "{report:?} vs {shortest}");
    assert!(report.px_per_mm > 0.8 * shortest, "{report:?} vs {shortest}");
    assert_eq!(out.width as f64, (40.0 * report.px_per_mm).round());
}

#[test]
fn bad_corners_and_sizes_are_refused() {
    let photo = Frame { width: 64, height: 48, rgb: vec![0.5; 64 * 48 * 3] };
    let ok = RectifyOptions {
        corners: [[4.0, 4.0], [60.0, 6.0], [58.0, 44.0], [3.0, 40.0]],
        size_mm: [10.0, 8.0],
        px_per_mm: None,
    };
    assert!(rectify(&photo, &ok).is_ok());
    let err = |o: RectifyOptions| rectify(&photo, &o).unwrap_err().to_string();
    let mut o = ok;
    o.corners[2] = [65.0, 44.0];
    assert!(err(o).contains("corner 2 at (65, 44) px lies outside"), "{}", err(o));
    let mut o = ok;
    o.corners.swap(1, 2);
    assert!(err(o).contains("not a convex quadrilateral"), "{}", err(o));
    let mut o = ok;
    o.corners[3] = [f64::NAN, 3.0];
    assert!(err(o).contains("corner 3"), "{}", err(o));
    o = ok;
    o.corners = [[1.0, 1.0], [3.0, 1.0], [3.0, 3.0], [1.0, 3.0]];
    assert!(err(o).contains("16 px²"), "{}", err(o));
    for size in [[0.0, 8.0], [10.0, f64::INFINITY], [-1.0, 1.0], [20_000.0, 1.0]] {
        assert!(err(RectifyOptions { size_mm: size, ..ok }).contains("--size-mm"), "{size:?}");
    }
    for d in [0.0, -2.0, f64::NAN] {
        assert!(err(RectifyOptions { px_per_mm: Some(d), ..ok }).contains("--px-per-mm"));
    }
    let big = err(RectifyOptions { px_per_mm: Some(5000.0), ..ok });
    assert!(big.contains("at most 16384 a side"), "{big}");
    let mut nan = photo.clone();
    nan.rgb[3 * (10 * 64 + 7) + 1] = f32::NAN;
    assert!(rectify(&nan, &ok).unwrap_err().to_string().contains("pixel (7, 10)"));
}
