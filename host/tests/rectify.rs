//! `host::build::rectify`: a photograph taken in perspective of a piece
//! whose pattern is known analytically, rectified back onto the piece.

use host::build::corners::{Origin, Polarity, find_corners, refine_corners};
use host::build::lens::{FrameMap, Lens, LensChoice, LensMap};
use host::build::linalg::Homography;
use host::build::rectify::{RectifyOptions, rectify};
use host::camera::Frame;

/// A pinhole camera's photographs.
const PINHOLE: LensChoice = LensChoice::Known(Lens::PINHOLE);

/// The piece's radiance at (x, y) mm: waves of 1.6–7 mm periods, in
/// [0.05, 0.95].
fn pattern(x: f64, y: f64) -> [f64; 3] {
    let a = (x * 1.1).sin() * (y * 0.9).cos();
    let b = (x * 2.3 + y * 3.1).sin();
    let c = (y * 3.9).cos();
    [0.5 + 0.3 * a + 0.15 * b, 0.5 + 0.45 * b, 0.5 + 0.2 * c + 0.25 * a]
        .map(|v| v.clamp(0.05, 0.95))
}

/// The pattern's mean over pixel (c, r) of a rectification at 4 px/mm
/// (8 × 8 points).
fn pattern_mean(c: usize, r: usize) -> [f64; 3] {
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
    want
}

const HOLDER: f32 = 10.0;
const SIZE_MM: [f64; 2] = [40.0, 24.0];

/// A `w × h` px photograph of the piece seen through `h_uv` (piece uv →
/// photograph px), each pixel the mean of 6 × 6 points; the holder around
/// the piece is far brighter than it.
fn photograph(w: u32, ht: u32, h_uv: &Homography) -> Frame {
    photograph_on(w, ht, h_uv, HOLDER as f64, |p| p)
}

/// The same on a holder of radiance `holder`, through a lens that shows at
/// px `q` what a pinhole shows at `lens(q)`.
fn photograph_on(
    w: u32,
    ht: u32,
    h_uv: &Homography,
    holder: f64,
    lens: impl Fn([f64; 2]) -> [f64; 2],
) -> Frame {
    photograph_of(w, ht, h_uv, holder, lens, pattern)
}

/// [`photograph_on`] of a piece of another `pattern` (radiance at x, y mm).
fn photograph_of(
    w: u32,
    ht: u32,
    h_uv: &Homography,
    holder: f64,
    lens: impl Fn([f64; 2]) -> [f64; 2],
    pattern: impl Fn(f64, f64) -> [f64; 3],
) -> Frame {
    let inv = h_uv.inverse().unwrap();
    let mut rgb = Vec::with_capacity((w * ht * 3) as usize);
    for y in 0..ht {
        for x in 0..w {
            let mut acc = [0.0f64; 3];
            for a in 0..6 {
                for b in 0..6 {
                    let p = [x as f64 + (a as f64 + 0.5) / 6.0, y as f64 + (b as f64 + 0.5) / 6.0];
                    let uv = inv.apply(lens(p));
                    let v = if uv.iter().all(|u| (0.0..1.0).contains(u)) {
                        pattern(uv[0] * SIZE_MM[0], uv[1] * SIZE_MM[1])
                    } else {
                        [holder; 3]
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
    let opts = RectifyOptions {
        corners: CORNERS,
        size_mm: SIZE_MM,
        px_per_mm: Some(4.0),
        lens: Lens::PINHOLE,
    };
    let (out, report) = rectify(&photo, &opts).unwrap();
    assert_eq!((out.width, out.height), (160, 96));
    assert!(report.supersampling >= 3, "{report:?}");
    // Against the pattern's mean over each output pixel (8 × 8 points).
    let (mut se, mut n, mut worst_edge) = (0.0f64, 0usize, 0.0f32);
    for r in 0..96usize {
        for c in 0..160usize {
            let want = pattern_mean(c, r);
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
        lens: Lens::PINHOLE,
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

/// A piece lying face up, u to the right and v up the photograph (a camera
/// does not mirror it): its corners uv (0, 0), (1, 0), (1, 1), (0, 1).
const FACE_UP: [[f64; 2]; 4] = [[130.0, 385.0], [515.0, 420.0], [560.0, 95.0], [100.0, 60.0]];
const DARK: f64 = 0.01;

fn face_up(corners: &[[f64; 2]; 4]) -> Homography {
    Homography::fit(&[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], corners).unwrap()
}

#[test]
fn the_corners_of_a_piece_on_a_dark_background_are_found() {
    let photo = photograph_on(640, 480, &face_up(&FACE_UP), DARK, |p| p);
    let found = find_corners(&photo, Origin::BottomLeft, PINHOLE).unwrap();
    // Measured: 0.026 px at worst (the photograph's pixels are means of
    // 6 × 6 points, so an edge is known to 1/12 px).
    let e = worst_px(&found.corners, &FACE_UP);
    eprintln!("{found:?}: {e:.3} px at worst");
    assert!(e <= 0.1, "{found:?}: {e:.3} px");
    assert!(found.edge_rms_px < 0.2 && found.edge_points > 1000, "{found:?}");
    assert!(found.contrast > 10.0, "{found:?}");
    // The piece turned: uv (0, 0) elsewhere, the order still
    // counter-clockwise as seen.
    for (k, origin) in [Origin::BottomLeft, Origin::TopLeft, Origin::TopRight, Origin::BottomRight]
        .iter()
        .enumerate()
    {
        let turned: [[f64; 2]; 4] = std::array::from_fn(|i| FACE_UP[(i + 4 - k) % 4]);
        let photo = photograph_on(640, 480, &face_up(&turned), DARK, |p| p);
        let found = find_corners(&photo, *origin, PINHOLE).unwrap();
        assert!(worst_px(&found.corners, &turned) <= 0.1, "{origin:?}: {found:?}");
    }

    // A dark piece on a white table: found the same way.
    let dark = photograph_on(640, 480, &face_up(&FACE_UP), 50.0, |p| p);
    let found_dark = find_corners(&dark, Origin::BottomLeft, PINHOLE).unwrap();
    let e = worst_px(&found_dark.corners, &FACE_UP);
    eprintln!("{found_dark:?}: {e:.3} px at worst");
    assert_eq!(found_dark.polarity, Polarity::Darker);
    assert!(e <= 0.1 && found_dark.contrast > 10.0, "{found_dark:?}: {e:.3} px");
    assert_eq!(found.polarity, Polarity::Brighter);

    // Rectified by the corners found, as by the true ones.
    let opts = RectifyOptions {
        corners: FACE_UP,
        size_mm: SIZE_MM,
        px_per_mm: Some(4.0),
        lens: Lens::PINHOLE,
    };
    let (want, _) = rectify(&photo_face_up(), &opts).unwrap();
    let (got, _) =
        rectify(&photo_face_up(), &RectifyOptions { corners: found.corners, ..opts }).unwrap();
    let se: f64 = want.rgb.iter().zip(&got.rgb).map(|(a, b)| (*a as f64 - *b as f64).powi(2)).sum();
    let psnr = 10.0 * (1.0 / (se / want.rgb.len() as f64)).log10();
    eprintln!("rectified by the corners found against the true ones: {psnr:.2} dB");
    assert!(psnr >= 50.0, "{psnr:.2} dB");
}

/// A checker of 4 mm squares of 0.1 and 1.2 (a glossy foil's shade and
/// highlights) on a background of 0.35.
fn foil(x: f64, y: f64) -> [f64; 3] {
    let odd = ((x / 4.0).floor() + (y / 4.0).floor()).rem_euclid(2.0) == 1.0;
    [if odd { 1.2 } else { 0.1 }; 3]
}

/// A piece both brighter and darker than its background: neither its
/// bright nor its dark parts make a quadrilateral, but where it differs
/// from the background either way does, and each side's profiles cross
/// its edge whichever way they differ.
#[test]
fn a_piece_brighter_and_darker_than_its_background_is_found() {
    let mixed = |lens: &dyn Fn([f64; 2]) -> [f64; 2], corners: &[[f64; 2]; 4]| {
        photograph_of(640, 480, &face_up(corners), 0.35, lens, foil)
    };
    let photo = mixed(&|p| p, &FACE_UP);
    let found = find_corners(&photo, Origin::BottomLeft, PINHOLE).unwrap();
    let e = worst_px(&found.corners, &FACE_UP);
    eprintln!("{found:?}: {e:.3} px at worst");
    // Measured 0.008 px (before: the dark square at a corner, 441 px off).
    assert_eq!(found.polarity, Polarity::Mixed);
    assert!(e <= 0.05, "{found:?}: {e:.3} px");
    assert!(found.contrast >= 2.0 && found.edge_points > 500, "{found:?}");
    // Through a lens, estimated from the same sides.
    let k = [-0.03, 0.0];
    let map = LensMap::new(Lens::radial(k), 640, 480).unwrap();
    let photo = mixed(&|q| map.in_pinhole(q), &FACE_UP);
    let corners = FACE_UP.map(|p| map.in_frame(p));
    let found = find_corners(&photo, Origin::BottomLeft, LensChoice::Estimate).unwrap();
    let e = worst_px(&found.corners, &corners);
    eprintln!("through k1 {}: {found:?}: {e:.3} px at worst", k[0]);
    assert_eq!(found.polarity, Polarity::Mixed);
    assert!(e <= 0.05 && (found.lens.k[0] - k[0]).abs() < 0.001, "{found:?}: {e:.3} px");
    // Marked 3 px off: refined the same way.
    let marked = corners.map(|[x, y]| [x + 3.0, y - 2.0]);
    let got = refine_corners(&photo, marked, LensChoice::Estimate).unwrap();
    let e = worst_px(&got.corners, &corners);
    eprintln!("marked: {got:?}: {e:.3} px at worst");
    assert_eq!(got.polarity, Polarity::Mixed);
    assert!(e <= 0.05, "{got:?}: {e:.3} px");
}

fn photo_face_up() -> Frame {
    photograph_on(640, 480, &face_up(&FACE_UP), DARK, |p| p)
}

#[test]
fn larger_regions_that_are_not_the_piece_are_passed_over() {
    // A small piece on the left; to its right a bright disc larger than
    // it and a bright card cut by the photograph's edge, larger still.
    let piece = [[60.0, 300.0], [220.0, 310.0], [230.0, 160.0], [70.0, 150.0]];
    let mut photo = photograph_on(800, 480, &face_up(&piece), DARK, |p| p);
    let paint = |photo: &mut Frame, on: &dyn Fn(f64, f64) -> bool| {
        for (i, px) in photo.rgb.chunks_exact_mut(3).enumerate() {
            if on((i % 800) as f64 + 0.5, (i / 800) as f64 + 0.5) {
                px.fill(0.6);
            }
        }
    };
    paint(&mut photo, &|x, y| (x - 450.0).hypot(y - 240.0) < 110.0);
    paint(&mut photo, &|x, _| x > 640.0);
    let found = find_corners(&photo, Origin::BottomLeft, PINHOLE).unwrap();
    eprintln!("{found:?}: {:.3} px at worst", worst_px(&found.corners, &piece));
    assert_eq!((found.polarity, found.passed_over), (Polarity::Brighter, 2), "{found:?}");
    assert!(worst_px(&found.corners, &piece) <= 0.1, "{found:?}");

    // Without the piece: refused, naming the largest region and why.
    let mut empty = photograph_on(800, 480, &face_up(&piece), DARK, |_| [-1e3, -1e3]);
    paint(&mut empty, &|x, y| (x - 450.0).hypot(y - 240.0) < 110.0);
    paint(&mut empty, &|x, _| x > 640.0);
    let why = find_corners(&empty, Origin::BottomLeft, PINHOLE).unwrap_err().to_string();
    assert!(
        why.contains("the largest bright region reaches the photograph's edge")
            && why
                .contains("no smaller one (of 1) lies whole in the photograph as a quadrilateral"),
        "{why}"
    );
}

#[test]
fn photographs_without_a_clear_piece_are_refused() {
    let find =
        |photo: &Frame| find_corners(photo, Origin::BottomLeft, PINHOLE).unwrap_err().to_string();
    let h = face_up(&FACE_UP);
    // Nothing in it.
    let uniform = Frame { width: 64, height: 48, rgb: vec![0.3; 64 * 48 * 3] };
    assert!(find(&uniform).contains("uniform"), "{}", find(&uniform));
    // Cut by the photograph's edge.
    let cut = photograph_on(480, 480, &h, DARK, |p| p);
    assert!(find(&cut).contains("reaches the photograph's edge"), "{}", find(&cut));
    // A plain piece on a background nearly as bright.
    let grey = {
        let inv = h.inverse().unwrap();
        let mut f = Frame { width: 640, height: 480, rgb: vec![0.0; 640 * 480 * 3] };
        for (i, px) in f.rgb.chunks_exact_mut(3).enumerate() {
            let (x, y) = ((i % 640) as f64, (i / 640) as f64);
            let mut v = 0.0;
            for a in 0..4 {
                for b in 0..4 {
                    let uv = inv.apply([x + (a as f64 + 0.5) / 4.0, y + (b as f64 + 0.5) / 4.0]);
                    let on = uv.iter().all(|u| (0.0..1.0).contains(u));
                    v += if on { 0.5 } else { 0.3 } / 16.0;
                }
            }
            px.fill(v);
        }
        f
    };
    assert!(find(&grey).contains("stands out"), "{}", find(&grey));
    // A disc is not a quadrilateral.
    let disc = {
        let mut f = Frame { width: 200, height: 200, rgb: vec![DARK as f32; 200 * 200 * 3] };
        for y in 0..200 {
            for x in 0..200 {
                if (x as f64 - 100.0).hypot(y as f64 - 100.0) < 70.0 {
                    f.rgb[3 * (y * 200 + x)..][..3].fill(0.6);
                }
            }
        }
        f
    };
    assert!(find(&disc).contains("not a quadrilateral"), "{}", find(&disc));
    // A square turned by 45°: which corner is uv (0, 0)?
    let diamond = [[320.0, 420.0], [480.0, 260.0], [320.0, 100.0], [160.0, 260.0]];
    let turned = photograph_on(640, 480, &face_up(&diamond), DARK, |p| p);
    assert!(find(&turned).contains("about 45°"), "{}", find(&turned));
    // Barrel distortion (the piece's corners 1.5 % further from the
    // photograph's centre, 3.6 px) bows its sides: refused, not fitted
    // (measured: a bow of 0.85 px, 0.47 px RMS).
    let barrel = photograph_on(640, 480, &h, DARK, |q| {
        let (x, y) = (q[0] - 320.0, q[1] - 240.0);
        let k = 1.0 + 2.6e-7 * (x * x + y * y);
        [320.0 + k * x, 240.0 + k * y]
    });
    assert!(find(&barrel).contains("not straight"), "{}", find(&barrel));
}

/// Whatever a photograph holds, finding the corners answers or refuses; it
/// never panics: noise, speckles, blocks, stripes, a single pixel or row,
/// zeros and huge values, seeded.
#[test]
fn finding_corners_never_panics() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(57);
    let (mut found, mut refused) = (0, 0);
    for case in 0..400 {
        let (w, h) = (rng.random_range(1..120u32), rng.random_range(1..120u32));
        let n = (w * h) as usize;
        let mut rgb = vec![0.0f32; n * 3];
        match case % 4 {
            0 => rgb.iter_mut().for_each(|v| *v = rng.random_range(0.0..1.0)),
            1 => {
                for _ in 0..rng.random_range(0..20) {
                    let i = rng.random_range(0..n);
                    rgb[3 * i..][..3].fill(rng.random_range(0.0..1e30));
                }
            }
            2 => {
                // Mostly with background round it.
                let (x0, y0) =
                    (rng.random_range(0..w.div_ceil(3)), rng.random_range(0..h.div_ceil(3)));
                let (x1, y1) = (rng.random_range(x0..=w), rng.random_range(y0..=h));
                for y in y0..y1 {
                    for x in x0..x1 {
                        let speck = rng.random_bool(0.02);
                        rgb[3 * (y * w + x) as usize..][..3].fill(if speck { 0.0 } else { 1.0 });
                    }
                }
            }
            _ => {
                let period = rng.random_range(1..6);
                for (i, px) in rgb.chunks_exact_mut(3).enumerate() {
                    px.fill(((i as u32 % w) / period % 2) as f32);
                }
            }
        }
        let photo = Frame { width: w, height: h, rgb };
        let origin = Origin::ALL[case % 4].1;
        match find_corners(&photo, origin, PINHOLE) {
            Ok(_) => found += 1,
            Err(_) => refused += 1,
        }
    }
    // Measured: 9 found (blocks with background round them), 391 refused.
    eprintln!("{found} found, {refused} refused");
    assert!(found > 0 && refused > 0);
}

/// A photograph as a phone on a table takes it: the piece turned by 12°,
/// light falling off by half towards the photograph's corners (on the
/// piece and the background alike), a soft shadow along two sides, and
/// noise of 3 % of the piece's level, seeded.
#[test]
fn the_corners_are_found_through_falloff_shadow_and_noise() {
    use rand::{Rng, SeedableRng};
    let (c, s) = (12f64.to_radians().cos(), 12f64.to_radians().sin());
    let (cx, cy, half) = (330.0, 235.0, 150.0);
    // Face up, turned: uv (0, 0) at the bottom left, u to the right.
    let corners: [[f64; 2]; 4] = [[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]]
        .map(|[x, y]| [cx + half * (c * x - s * y), cy + half * (s * x + c * y)]);
    let clean = photograph_on(640, 480, &face_up(&corners), 0.03, |p| p);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
    let mut photo = clean.clone();
    let inside = |x: f64, y: f64| {
        (0..4).all(|k| {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) <= 0.0
        })
    };
    for (i, px) in photo.rgb.chunks_exact_mut(3).enumerate() {
        let (x, y) = ((i % 640) as f64 + 0.5, (i / 640) as f64 + 0.5);
        let r2 = ((x - 320.0).powi(2) + (y - 240.0).powi(2)) / (400.0f64).powi(2);
        let falloff = 1.0 / (1.0 + r2);
        // The shadow: the background darker within 6 px below and right
        // of the piece (the light from the top left).
        let shade = if !inside(x, y) && inside(x - 4.0, y - 4.0) { 0.4 } else { 1.0 };
        for v in px.iter_mut() {
            let noise = 0.03 * 0.5 * rng.random_range(-1.7..1.7);
            *v = ((*v as f64 * shade * falloff) + noise).max(0.0) as f32;
        }
    }
    let found = find_corners(&photo, Origin::BottomLeft, PINHOLE).unwrap();
    let worst = worst_px(&found.corners, &corners);
    // Measured: 0.12 px at worst.
    eprintln!("{found:?}: {worst:.3} px at worst");
    assert!(worst <= 0.25, "{found:?} against {corners:?}: {worst:.3} px");
}

/// Corners marked by hand within a few pixels move onto the piece's
/// edges, in the order they were marked (here the region images' mirrored
/// order, which `--corners auto` cannot give), on a dark background and on
/// a light one.
#[test]
fn marked_corners_are_refined_onto_the_edges() {
    // Marks 2–4 px off, seeded.
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    for holder in [DARK, 50.0] {
        let photo = photograph_on(640, 480, &face_up(&CORNERS), holder, |p| p);
        let marked = CORNERS.map(|[x, y]| {
            let (r, a) = (rng.random_range(2.0..4.0), rng.random_range(0.0..std::f64::consts::TAU));
            [x + r * a.cos(), y + r * a.sin()]
        });
        let got = refine_corners(&photo, marked, PINHOLE).unwrap();
        let worst = worst_px(&got.corners, &CORNERS);
        // Measured: 0.03 px at worst on either.
        eprintln!("holder {holder}: {got:?}: {worst:.3} px at worst");
        assert!(worst <= 0.1, "holder {holder}: {got:?}: {worst:.3} px");
        let want = if holder == DARK { Polarity::Brighter } else { Polarity::Darker };
        assert_eq!(got.polarity, want);
    }
    // Marks nowhere near an edge, or not a quadrilateral: refused.
    let photo = photograph_on(640, 480, &face_up(&CORNERS), DARK, |p| p);
    let inner = [[200.0, 150.0], [400.0, 160.0], [390.0, 300.0], [210.0, 290.0]];
    let err = refine_corners(&photo, inner, PINHOLE).unwrap_err().to_string();
    assert!(err.contains("refining the marked corners"), "{err}");
    let crossed = [CORNERS[0], CORNERS[2], CORNERS[1], CORNERS[3]];
    let err = refine_corners(&photo, crossed, PINHOLE).unwrap_err().to_string();
    assert!(err.contains("not a convex quadrilateral"), "{err}");
}

/// A photograph through a lens with radial distortion `k` (half-diagonal
/// scale) of the piece whose pinhole corners are `pinhole`: the photograph
/// and the corners as it shows them.
fn through_lens(k: [f64; 2], pinhole: &[[f64; 2]; 4]) -> (Frame, [[f64; 2]; 4], LensMap) {
    let map = LensMap::new(Lens::radial(k), 640, 480).unwrap();
    let photo = photograph_on(640, 480, &face_up(pinhole), DARK, |q| map.in_pinhole(q));
    (photo, pinhole.map(|p| map.in_frame(p)), map)
}

fn worst_px(a: &[[f64; 2]; 4], b: &[[f64; 2]; 4]) -> f64 {
    (0..4).map(|k| (a[k][0] - b[k][0]).hypot(a[k][1] - b[k][1])).fold(0.0, f64::max)
}

/// PSNR (peak 1) of a rectification of the piece at 4 px/mm against the
/// pattern's mean over each output pixel, border pixels left out.
fn psnr_against_pattern(out: &Frame) -> f64 {
    let (w, h) = (out.width as usize, out.height as usize);
    let (mut se, mut n) = (0.0f64, 0usize);
    for r in 1..h - 1 {
        for c in 1..w - 1 {
            let want = pattern_mean(c, r);
            for (got, want) in out.rgb[3 * (r * w + c)..][..3].iter().zip(want) {
                se += (*got as f64 - want).powi(2);
                n += 1;
            }
        }
    }
    10.0 * (1.0 / (se / n as f64)).log10()
}

/// The options rectifying the piece at 4 px/mm by `corners` through
/// `lens`.
fn at_4(corners: [[f64; 2]; 4], lens: Lens) -> RectifyOptions {
    RectifyOptions { corners, size_mm: SIZE_MM, px_per_mm: Some(4.0), lens }
}

/// [`psnr_against_pattern`] of a pinhole's photograph of the piece,
/// rectified by its true corners.
fn pinhole_psnr() -> f64 {
    let pinhole = photograph_on(640, 480, &face_up(&FACE_UP), DARK, |p| p);
    psnr_against_pattern(&rectify(&pinhole, &at_4(FACE_UP, Lens::PINHOLE)).unwrap().0)
}

/// Through a lens with barrel or pincushion distortion the piece's sides
/// bow: `--lens auto` estimates k1 from them (the plumb-line method on the
/// piece's own sides), finds the corners where the photograph shows them,
/// and the rectification through the lens matches the pattern as a
/// pinhole photograph's does; ignoring the lens costs.
#[test]
fn a_lens_is_estimated_from_the_pieces_sides_and_rectified_through() {
    let base = pinhole_psnr();
    for k1 in [-0.06, -0.02, 0.04] {
        let (photo, corners, _) = through_lens([k1, 0.0], &FACE_UP);
        // Straight lines refused without the lens (but for the mildest).
        let plain = find_corners(&photo, Origin::BottomLeft, PINHOLE);
        if k1 != -0.02 {
            let e = plain.unwrap_err().to_string();
            assert!(e.contains("not straight"), "k1 {k1}: {e}");
        }
        let found = find_corners(&photo, Origin::BottomLeft, LensChoice::Estimate).unwrap();
        let e = worst_px(&found.corners, &corners);
        let known = LensChoice::Known(Lens::radial([k1, 0.0]));
        let given = find_corners(&photo, Origin::BottomLeft, known).unwrap();
        let g = worst_px(&given.corners, &corners);
        let (got, _) = rectify(&photo, &at_4(found.corners, found.lens)).unwrap();
        let psnr = psnr_against_pattern(&got);
        // The true corners, the lens ignored.
        let (ignored, _) = rectify(&photo, &at_4(corners, Lens::PINHOLE)).unwrap();
        let without = psnr_against_pattern(&ignored);
        eprintln!(
            "k1 {k1}: estimated {:.5}, corners within {e:.3} px ({g:.3} px with the lens \
             given); rectified {psnr:.2} dB, the lens ignored {without:.2} dB, a pinhole's \
             {base:.2} dB",
            found.lens.k[0]
        );
        assert!((found.lens.k[0] - k1).abs() < 1e-3, "k1 {k1}: {found:?}");
        // Its standard error says about how far off it is.
        let sigma = found.lens_k1_sigma.unwrap();
        eprintln!("k1 {k1}: σ {sigma:.5}");
        assert!(sigma > 0.0 && sigma < 1e-3 && (found.lens.k[0] - k1).abs() < 3.0 * sigma);
        assert_eq!(given.lens_k1_sigma, None);
        assert!(e <= 0.1 && g <= 0.1, "k1 {k1}: {e:.3} / {g:.3} px");
        assert!(found.bow_px < 0.2, "k1 {k1}: {found:?}");
        assert!(psnr >= base - 3.0, "k1 {k1}: {psnr:.2} against {base:.2} dB");
        assert!(without < psnr - 10.0, "k1 {k1}: {without:.2} against {psnr:.2} dB");
        // Marks a few px off, refined through an estimated lens.
        let marked = corners.map(|[x, y]| [x + 2.5, y - 2.0]);
        let refined = refine_corners(&photo, marked, LensChoice::Estimate).unwrap();
        let r = worst_px(&refined.corners, &corners);
        assert!(r <= 0.1 && (refined.lens.k[0] - k1).abs() < 1e-3, "k1 {k1}: {refined:?}");
    }
    // The pinhole photograph's lens comes out as none.
    let pinhole = photograph_on(640, 480, &face_up(&FACE_UP), DARK, |p| p);
    let found = find_corners(&pinhole, Origin::BottomLeft, LensChoice::Estimate).unwrap();
    assert!(found.lens.k[0].abs() < 1e-3, "{found:?}");
    assert!(worst_px(&found.corners, &FACE_UP) <= 0.1, "{found:?}");
}

/// A calibration's lens about a principal point off the photograph's
/// centre (OpenCV's cx, cy: `--lens K1,K2,F,CX,CY`): given whole, the
/// piece rectifies as through a pinhole; taken about the centre instead,
/// it does not.
#[test]
fn a_principal_point_off_the_centre_is_rectified_through() {
    let base = pinhole_psnr();
    let lens = Lens {
        focal_px: Some(700.0),
        centre_px: Some([290.0, 262.0]),
        ..Lens::radial([-0.12, 0.02])
    };
    let map = LensMap::new(lens, 640, 480).unwrap();
    let photo = photograph_on(640, 480, &face_up(&FACE_UP), DARK, |q| map.in_pinhole(q));
    let corners = FACE_UP.map(|p| map.in_frame(p));
    let found = find_corners(&photo, Origin::BottomLeft, LensChoice::Known(lens)).unwrap();
    let worst = worst_px(&found.corners, &corners);
    let (got, _) = rectify(&photo, &at_4(found.corners, lens)).unwrap();
    let psnr = psnr_against_pattern(&got);
    let centred = Lens { centre_px: None, ..lens };
    let (off, _) = rectify(&photo, &at_4(corners, centred)).unwrap();
    let about_centre = psnr_against_pattern(&off);
    eprintln!(
        "corners within {worst:.3} px; rectified {psnr:.2} dB (a pinhole's {base:.2} dB), the \
         lens taken about the photograph's centre {about_centre:.2} dB"
    );
    assert!(worst <= 0.1, "{found:?}");
    assert!(psnr >= base - 3.0, "{psnr:.2} against {base:.2} dB");
    assert!(about_centre < psnr - 10.0, "{about_centre:.2} against {psnr:.2} dB");
}

/// A plain card (no pattern: a white reference) in a small photograph
/// through a lens, each pixel the mean of 16 × 16 points as a sensor's
/// area would give: its sides are placed within their pixels by the
/// piece's share of each profile, so k1 comes out within 3 · 10⁻⁴
/// (measured: 0.00000 and 0.00009; corners within 0.001 px), where the
/// level's crossing of the interpolated profile, off by up to 0.08 px
/// with the edge's phase in the pixels, gave −0.0333 for −0.03 (corners
/// 0.054 px).
#[test]
fn a_plain_cards_sides_give_the_lens_in_a_small_photograph() {
    let (w, h) = (180u32, 180u32);
    let pinhole = [[40.0, 140.0], [143.0, 146.0], [140.0, 35.0], [37.0, 41.0]];
    for k1 in [-0.03, 0.03] {
        let map = LensMap::new(Lens::radial([k1, 0.0]), w, h).unwrap();
        let inv = face_up(&pinhole).inverse().unwrap();
        let mut rgb = Vec::with_capacity((w * h * 3) as usize);
        for y in 0..h {
            for x in 0..w {
                let mut on = 0usize;
                for a in 0..16 {
                    for b in 0..16 {
                        let q = [
                            x as f64 + (a as f64 + 0.5) / 16.0,
                            y as f64 + (b as f64 + 0.5) / 16.0,
                        ];
                        let uv = inv.apply(map.in_pinhole(q));
                        on += uv.iter().all(|u| (0.0..1.0).contains(u)) as usize;
                    }
                }
                let v = DARK + (0.8 - DARK) * on as f64 / 256.0;
                rgb.extend([v as f32; 3]);
            }
        }
        let photo = Frame { width: w, height: h, rgb };
        let found = find_corners(&photo, Origin::BottomLeft, LensChoice::Estimate).unwrap();
        let corners = pinhole.map(|p| map.in_frame(p));
        let (e, sigma) = (found.lens.k[0] - k1, found.lens_k1_sigma.unwrap());
        let worst = worst_px(&found.corners, &corners);
        eprintln!(
            "k1 {k1}: estimated {:.5} ± {sigma:.5}, corners within {worst:.4} px",
            found.lens.k[0]
        );
        assert!(e.abs() < 3e-4, "k1 {k1}: {found:?}");
        assert!(worst < 0.02, "k1 {k1}: {worst:.4} px");
    }
}

/// A lens of another form than the model's (the pinhole point a cubic of
/// the photograph's radius: barrel distortion of 3.6 px at the corners
/// where the model's own inverse is not a polynomial): estimated to the
/// model's nearest, the corners within a tenth of a pixel.
#[test]
fn a_lens_of_another_form_is_estimated_near_enough() {
    let photo = photograph_on(640, 480, &face_up(&FACE_UP), DARK, |q| {
        let (x, y) = (q[0] - 320.0, q[1] - 240.0);
        let k = 1.0 + 2.6e-7 * (x * x + y * y);
        [320.0 + k * x, 240.0 + k * y]
    });
    // Where the photograph shows the pinhole corners: the inverse, by
    // bisection along the radius.
    let shown = FACE_UP.map(|p| {
        let (x, y) = (p[0] - 320.0, p[1] - 240.0);
        let r = x.hypot(y);
        let (mut lo, mut hi) = (0.0, r);
        for _ in 0..100 {
            let mid = 0.5 * (lo + hi);
            if mid * (1.0 + 2.6e-7 * mid * mid) < r { lo = mid } else { hi = mid }
        }
        [320.0 + x * lo / r, 240.0 + y * lo / r]
    });
    let found = find_corners(&photo, Origin::BottomLeft, LensChoice::Estimate).unwrap();
    let e = worst_px(&found.corners, &shown);
    eprintln!("estimated k1 {:.5}; corners within {e:.3} px", found.lens.k[0]);
    assert!(e <= 0.1, "{found:?} against {shown:?}: {e:.3} px");
}

/// `--lens` values that fold the photograph are refused.
#[test]
fn a_lens_that_folds_the_photograph_is_refused_by_rectify() {
    let photo = photograph_on(640, 480, &face_up(&FACE_UP), DARK, |p| p);
    let opts = RectifyOptions {
        corners: FACE_UP,
        size_mm: SIZE_MM,
        px_per_mm: Some(4.0),
        lens: Lens::radial([-0.5, 0.0]),
    };
    let err = rectify(&photo, &opts).unwrap_err().to_string();
    assert!(err.contains("one to one"), "{err}");
}
