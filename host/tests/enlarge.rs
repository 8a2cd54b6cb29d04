//! `host::build::enlarge` on synthetic materials and direct images made from
//! them: a piece that is the sample tiled is mapped back onto the sample
//! texel for texel; a featureless sample matches without trouble.

#[path = "../benches/support/synthetic.rs"]
#[allow(dead_code)] // not every helper is used here
mod synthetic;

use host::build::enlarge::{DirectSet, EnlargeOptions, Signature, enlarge};
use host::camera::Frame;
use scanner_formats::direct::{DirectImage, DirectManifest, FORMAT, WhiteImage};
use scanner_shading::{Interpolation, Material, MaterialData};
use synthetic::{Shape, synthetic};

/// Direct images of a piece made of `tiles` × `tiles` copies of `data`'s
/// sample, shaded by the material itself from the first four mirror
/// directions at `px` pixels per sample texel, with a white reference
/// that makes the scale exactly 1.
fn tiled_set(data: &MaterialData, tiles: usize, px: usize) -> DirectSet {
    let m = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
    let s = data.meta.resolution as usize;
    let n = tiles * s * px;
    let dirs: Vec<[f64; 3]> = data.meta.views[..4].iter().map(|v| v.direction).collect();
    let exposure_s = 0.25;
    let images = dirs
        .iter()
        .map(|d| {
            let d32 = d.map(|x| x as f32);
            let mut rgb = Vec::with_capacity(n * n * 3);
            for y in 0..n {
                for x in 0..n {
                    // The pixel's centre on the sample, in sample texels.
                    let at = |p: usize| ((p % (s * px)) as f32 + 0.5) / px as f32 / s as f32;
                    let v = m.eval([at(x), at(y)], d32, d32);
                    rgb.extend(v.map(|c| c * exposure_s as f32));
                }
            }
            Frame { width: n as u32, height: n as u32, rgb }
        })
        .collect();
    let albedo = 0.9;
    let cos = dirs[0][2];
    let level = (albedo / std::f64::consts::PI * cos * exposure_s) as f32;
    let white = Frame { width: 8, height: 8, rgb: vec![level; 8 * 8 * 3] };
    let side = tiles as f64 * data.meta.sample_size_mm;
    let manifest = DirectManifest {
        format: FORMAT,
        size_mm: [side, side],
        image: dirs
            .iter()
            .enumerate()
            .map(|(k, &direction)| DirectImage {
                file: format!("d{k}.exr"),
                direction,
                exposure_s,
                mirror: None,
                camera_distance_mm: None,
            })
            .collect(),
        white: Some(WhiteImage { file: "w.exr".into(), direction: dirs[0], exposure_s, albedo }),
    };
    DirectSet { manifest, images, white: Some(white), sha256: "0".repeat(64) }
}

fn shape(resolution: usize) -> Shape {
    Shape { mirrors: 12, resolution, colours: 64, lights_per_index: 1 }
}

#[test]
fn a_piece_tiled_from_the_sample_maps_back_onto_it() {
    let data = synthetic(&shape(12), Interpolation::Default, 0.0, 3);
    let s = 12usize;
    for subtexel in [1, 2] {
        let set = tiled_set(&data, 3, 4);
        let opts = EnlargeOptions { subtexel, ..EnlargeOptions::DEFAULT };
        let (big, report) = enlarge(&data, &set, &opts).unwrap();
        assert_eq!((report.columns, report.rows), (36, 36));
        for g in report.gain.unwrap() {
            assert!((g - 1.0).abs() < 1e-6, "{g}: the white reference's scale");
        }
        let e = big.meta.enlargement.as_ref().unwrap();
        assert_eq!((e.columns, e.rows, e.directions.len()), (36, 36, 4));
        assert!(big.meta.extent_mm.iter().all(|x| (x - 76.2).abs() < 1e-9));
        // Every texel whose 3 × 3 neighbourhood lies within one tile (the
        // clamped borders and the seams differ) matches its own place.
        let mut wrong = Vec::new();
        for r in 0..36 {
            for c in 0..36 {
                let (x, y) = (c % s, r % s);
                if x == 0 || y == 0 || x == s - 1 || y == s - 1 {
                    continue;
                }
                let m = big.enlargement[r * 36 + c];
                let want = [x, y].map(|k| (k as f64 + 0.5) / s as f64);
                let got = m.map(|v| (v as f64 + 0.5) / 65536.0);
                if (0..2).any(|k| (got[k] - want[k]).abs() > 1e-4) {
                    wrong.push(((c, r), got, want));
                }
            }
        }
        assert!(
            wrong.is_empty(),
            "subtexel {subtexel}: {} wrong: {:?}",
            wrong.len(),
            &wrong[..wrong.len().min(5)]
        );
        assert!(report.distance[0] < 1e-3, "{:?}", report.distance);
        // And the enlarged material shades each texel centre of the piece
        // as the sample's material shades its match.
        let (small, large) = (
            Material::from_bytes(&data.to_bytes().unwrap()).unwrap(),
            Material::from_bytes(&big.to_bytes().unwrap()).unwrap(),
        );
        let (wi, wo) = ([0.2, 0.1, 0.97], [-0.3, 0.2, 0.93]);
        for (c, r) in [(13usize, 14usize), (30, 5), (7, 26)] {
            let uv = [(c as f32 + 0.5) / 36.0, (r as f32 + 0.5) / 36.0];
            let on_sample = [(c % s) as f32 + 0.5, (r % s) as f32 + 0.5].map(|k| k / s as f32);
            let (a, b) = (large.eval(uv, wi, wo), small.eval(on_sample, wi, wo));
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() <= 1e-4 * b[k].abs().max(1e-2), "{a:?} {b:?}");
            }
        }
    }
}

#[test]
fn without_a_white_reference_the_scale_comes_from_the_images() {
    let data = synthetic(&shape(16), Interpolation::Default, 0.0, 5);
    let mut set = tiled_set(&data, 3, 2);
    // A camera of its own scale: 3.7 × brighter, no white reference.
    for im in &mut set.images {
        im.rgb.iter_mut().for_each(|v| *v *= 3.7);
    }
    (set.white, set.manifest.white) = (None, None);
    let (_, report) = enlarge(&data, &set, &EnlargeOptions::DEFAULT).unwrap();
    for g in report.gain.unwrap() {
        assert!((g * 3.7 - 1.0).abs() < 0.02, "{g}");
    }
}

#[test]
fn the_height_signature_maps_a_tiled_piece_back_at_any_scale() {
    let data = synthetic(&shape(16), Interpolation::Default, 0.0, 11);
    let s = 16usize;
    let mut set = tiled_set(&data, 3, 2);
    // Another camera's scale and no white reference: heights do not mind.
    for im in &mut set.images {
        im.rgb.iter_mut().for_each(|v| *v *= 3.7);
    }
    (set.white, set.manifest.white) = (None, None);
    for radius in [1, 2] {
        let opts =
            EnlargeOptions { radius, signature: Signature::Height, ..EnlargeOptions::DEFAULT };
        let (big, report) = enlarge(&data, &set, &opts).unwrap();
        assert_eq!(report.gain, None);
        assert_eq!(big.meta.enlargement.as_ref().unwrap().signature, "height");
        // The piece's heights are integrated over the piece and the
        // sample's over the sample, so texels near a tile's border see
        // other surroundings; those 2 texels or more inside a tile match
        // their own place.
        let share = own_place_share(&big, s);
        assert!(share > 0.9, "radius {radius}: {share} of the texels matched their place");
    }
    let opts =
        EnlargeOptions { radius: 0, signature: Signature::Height, ..EnlargeOptions::DEFAULT };
    let err = enlarge(&data, &set, &opts).unwrap_err().to_string();
    assert!(err.contains("--radius 0 leaves the height signature empty"), "{err}");
    // Photometric stereo needs three directions not in one plane.
    set.images.truncate(2);
    set.manifest.image.truncate(2);
    let opts = EnlargeOptions { signature: Signature::Height, ..EnlargeOptions::DEFAULT };
    let err = enlarge(&data, &set, &opts).unwrap_err().to_string();
    assert!(err.contains("not in one plane"), "{err}");
}

/// The share of the piece's texels 2 or more inside a tile (of `s`
/// texels; the piece 3 × 3 tiles) that the map sends to their own place on
/// the sample.
fn own_place_share(big: &MaterialData, s: usize) -> f64 {
    let (mut inside, mut own) = (0, 0);
    for r in 0..3 * s {
        for c in 0..3 * s {
            let (x, y) = (c % s, r % s);
            if [x, y].iter().any(|&k| k < 2 || k + 2 >= s) {
                continue;
            }
            inside += 1;
            let want = [x, y].map(|k| (k as f64 + 0.5) / s as f64);
            let got = big.enlargement[r * 3 * s + c].map(|v| (v as f64 + 0.5) / 65536.0);
            own += usize::from((0..2).all(|k| (got[k] - want[k]).abs() < 1e-4));
        }
    }
    own as f64 / inside as f64
}

/// A piece of the sample's relief with another albedo: each point's
/// values multiplied by a smooth factor of its own (0.6–1.65×, the same
/// under every light), as a piece faded or dyed darker in places. Heights,
/// from normals that photometric stereo finds whatever the albedo, match
/// more texels to their own place than colours do. Dyed per channel (the
/// factor differing between R, G and B) the synthetic material, whose
/// colours change with the direction in no physical way, loses its
/// photometric stereo instead: measured, not asserted beyond that.
#[test]
fn a_piece_of_the_same_relief_with_another_albedo_matches_by_height() {
    let data = synthetic(&shape(16), Interpolation::Default, 0.0, 11);
    let s = 16usize;
    let tau = std::f64::consts::TAU;
    // The dye of channel c at (x, y) over the piece (0…1), per channel or
    // grey.
    let dyed = |per_channel: bool| {
        let mut set = tiled_set(&data, 3, 2);
        let n = set.images[0].width as usize;
        for im in &mut set.images {
            for (i, px) in im.rgb.chunks_exact_mut(3).enumerate() {
                let (x, y) = ((i % n) as f64 / n as f64, (i / n) as f64 / n as f64);
                for (c, v) in px.iter_mut().enumerate() {
                    let c = if per_channel { c as f64 } else { 0.0 };
                    let f = (tau * 1.3 * x + c).sin() * (tau * 0.9 * y - 2.0 * c).cos();
                    *v *= (0.5 * f).exp() as f32;
                }
            }
        }
        set
    };
    let share = |set: &DirectSet, signature| {
        let opts = EnlargeOptions { signature, radius: 1, ..EnlargeOptions::DEFAULT };
        own_place_share(&enlarge(&data, set, &opts).unwrap().0, s)
    };
    let grey = dyed(false);
    let (by_colour, by_height) = (share(&grey, Signature::Colour), share(&grey, Signature::Height));
    // Measured: 0.840 by colour, 0.974 by height.
    eprintln!("another albedo: own place by colour {by_colour:.3}, by height {by_height:.3}");
    assert!(by_height > 0.95, "{by_height}");
    assert!(by_colour < by_height - 0.1, "{by_colour} against {by_height}");
    let per_channel = dyed(true);
    let (by_colour, by_height) =
        (share(&per_channel, Signature::Colour), share(&per_channel, Signature::Height));
    // Measured: 0.971 by colour, 0.721 by height.
    eprintln!("dyed per channel: own place by colour {by_colour:.3}, by height {by_height:.3}");
    assert!(by_colour > 0.9 && by_height < by_colour, "{by_colour} against {by_height}");
}

#[test]
fn a_featureless_sample_and_bad_sets_are_handled() {
    // Every palette colour alike: all candidate signatures are equal.
    let mut data = synthetic(&shape(8), Interpolation::Default, 0.0, 7);
    for p in &mut data.palettes {
        *p = [0.1, 0.1, 0.1];
    }
    let set = tiled_set(&data, 2, 1);
    let (big, report) = enlarge(&data, &set, &EnlargeOptions::DEFAULT).unwrap();
    assert_eq!(big.enlargement.len(), 16 * 16);
    assert!(report.distance[1] < 1e-3);
    // Enlarging again is refused; so are options out of range and a black
    // white reference or black images.
    let err = |d: &MaterialData, set: &DirectSet, o: EnlargeOptions| {
        enlarge(d, set, &o).unwrap_err().to_string()
    };
    assert!(err(&big, &set, EnlargeOptions::DEFAULT).contains("enlarged already"));
    let o = EnlargeOptions { radius: 4, ..EnlargeOptions::DEFAULT };
    assert!(err(&data, &set, o).contains("--radius 4"));
    let o = EnlargeOptions { subtexel: 0, ..EnlargeOptions::DEFAULT };
    assert!(err(&data, &set, o).contains("--subtexel 0"));
    let mut black = set.clone();
    black.white.as_mut().unwrap().rgb.iter_mut().for_each(|v| *v = 0.0);
    assert!(err(&data, &black, EnlargeOptions::DEFAULT).contains("not a white reference"));
    let mut dark = set.clone();
    dark.images.iter_mut().for_each(|im| im.rgb.iter_mut().for_each(|v| *v = 0.0));
    assert!(err(&data, &dark, EnlargeOptions::DEFAULT).contains("is black"));
}

#[test]
fn an_enlarged_material_exports_maps_of_its_whole_piece() {
    let data =
        synthetic::with_texel_model(synthetic(&shape(12), Interpolation::Default, 0.0, 9), 10);
    let set = tiled_set(&data, 3, 4);
    let (big, _) = enlarge(&data, &set, &EnlargeOptions::DEFAULT).unwrap();
    let small = host::build::export::texture_set(&data).unwrap();
    let large = host::build::export::texture_set(&big).unwrap();
    assert_eq!((small.side, large.side), (12, 36));
    assert!((small.size_mm - 25.4).abs() < 1e-9 && (large.size_mm - 76.2).abs() < 1e-9);
    // Each texel of the piece (away from the tiles' seams) is its match's,
    // but for the map's 16-bit rounding (10⁻⁴ of a texel).
    for (c, r) in [(13usize, 14usize), (30, 5), (7, 26), (22, 22)] {
        let (i, j) = (r * 36 + c, (r % 12) * 12 + c % 12);
        for k in 0..3 {
            assert!(
                (large.diffuse[i][k] - small.diffuse[j][k]).abs() < 5e-4,
                "({c}, {r}): {:?} {:?}, map {:?}",
                large.diffuse[i],
                small.diffuse[j],
                big.enlargement[i].map(|v| (v as f64 + 0.5) / 65536.0 * 12.0)
            );
            assert!((large.specular[i][k] - small.specular[j][k]).abs() < 5e-4, "({c}, {r})");
            assert!((large.normal[i][k] - small.normal[j][k]).abs() < 5e-4, "({c}, {r})");
        }
        assert!((large.roughness[i] - small.roughness[j]).abs() < 5e-4, "({c}, {r})");
    }
    // A map that is not square over its square piece has no square maps.
    let mut oblong = big.clone();
    let e = oblong.meta.enlargement.as_mut().unwrap();
    (e.columns, e.rows) = (72, 18);
    let err = host::build::export::texture_set(&oblong).unwrap_err().to_string();
    assert!(err.contains("72 × 18 texels over a square"), "{err}");
}
