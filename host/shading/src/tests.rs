use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::format::{CellTable, Mirror, Provenance};
use super::*;

/// The zenith and a ring of six at 40°: six fan triangles.
fn ring() -> (Vec<[f64; 3]>, Vec<[u16; 3]>) {
    let mut dirs = vec![[0.0, 0.0, 1.0]];
    for k in 0..6 {
        let phi = k as f64 * std::f64::consts::TAU / 6.0;
        let t = 40f64.to_radians();
        dirs.push([t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()]);
    }
    let tris = (0..6).map(|k| [0, 1 + k as u16, 1 + ((k + 1) % 6) as u16]).collect();
    (dirs, tris)
}

fn mirrors(d: &[[f64; 3]]) -> Vec<Mirror> {
    d.iter().enumerate().map(|(i, &direction)| Mirror { mirror: i as u32, direction }).collect()
}

/// A material whose every texel of pair (l, v) has colour
/// (l + 1, v + 1, texel column) / 100 · cos θ_l, one colour per
/// (pair, column): K = S.
fn material(interpolation: Interpolation) -> MaterialData {
    let (dirs, tris) = ring();
    let (n, s, g) = (dirs.len(), 8usize, 2usize);
    let k = s;
    let groups = n.div_ceil(g);
    let mut palettes = Vec::new();
    for (l, dl) in dirs.iter().enumerate() {
        for v in 0..n {
            for c in 0..k {
                let cos = dl[2] as f32;
                palettes.push([
                    (l + 1) as f32 / 100.0 * cos,
                    (v + 1) as f32 / 100.0 * cos,
                    c as f32 / 100.0 * cos,
                ]);
            }
        }
    }
    let mut indices = vec![0u8; n * s * s * groups];
    for v in 0..n {
        for t in 0..s {
            for c in 0..s {
                for grp in 0..groups {
                    indices[((v * s + t) * s + c) * groups + grp] = c as u8;
                }
            }
        }
    }
    let tables = match interpolation {
        Interpolation::Default => DirectionTables::Triangles { views: tris.clone(), lights: tris },
        Interpolation::Patent { columns, rows, points } => {
            // Every cell: the nearest direction with all the points.
            let mut t = CellTable { offsets: vec![0], ..Default::default() };
            for r in 0..rows {
                for c in 0..columns {
                    let th = (r as f64 + 0.5) / rows as f64 * std::f64::consts::FRAC_PI_2;
                    let ph = (c as f64 + 0.5) / columns as f64 * std::f64::consts::TAU;
                    let d = [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()];
                    let best = (0..n)
                        .max_by(|&a, &b| {
                            let da: f64 = (0..3).map(|i| d[i] * dirs[a][i]).sum();
                            let db: f64 = (0..3).map(|i| d[i] * dirs[b][i]).sum();
                            da.total_cmp(&db)
                        })
                        .unwrap();
                    t.mirrors.push(best as u16);
                    t.counts.push(points as u16);
                    t.offsets.push(t.mirrors.len() as u32);
                }
            }
            DirectionTables::Patent { views: t.clone(), lights: t }
        }
    };
    MaterialData {
        meta: Metadata {
            format: format::FORMAT.into(),
            version: format::VERSION,
            name: "test".into(),
            sample_size_mm: 25.4,
            extent_mm: [25.4, 25.4],
            resolution: s as u32,
            colours: k as u32,
            lights_per_index: g as u32,
            interpolation,
            half_vector_shift: 1.0,
            lights: mirrors(&dirs),
            views: mirrors(&dirs),
            provenance: Provenance {
                scan_manifest_sha256: "0".repeat(64),
                geometry_sha256: "1".repeat(64),
                calibration_sha256: "2".repeat(64),
                builder: "test".into(),
                face: None,
            },
            texel_model: false,
            detail: false,
            detail_components: 0,
            enlargement: None,
        },
        palettes,
        indices,
        light_groups: (0..n).map(|l| (l / g) as u8).collect(),
        tables,
        texels: Vec::new(),
        detail: Vec::new(),
        detail_bases: Vec::new(),
        detail_coefficients: Vec::new(),
        enlargement: Vec::new(),
    }
}

fn f32v(d: [f64; 3]) -> [f32; 3] {
    d.map(|x| x as f32)
}

fn close(a: [f32; 3], b: [f32; 3], tol: f32) -> bool {
    (0..3).all(|k| (a[k] - b[k]).abs() <= tol * b[k].abs().max(1e-3))
}

#[test]
fn captured_pairs_are_returned_exactly() {
    let m = Material::from_bytes(&material(Interpolation::Default).to_bytes().unwrap()).unwrap();
    let (dirs, _) = ring();
    for (l, dl) in dirs.iter().enumerate() {
        for (v, dv) in dirs.iter().enumerate() {
            // Texel column 3's centre.
            let uv = [3.5 / 8.0, 0.3];
            let got = m.eval(uv, f32v(*dl), f32v(*dv));
            let cos = dl[2] as f32;
            let want = [(l + 1) as f32 / 100.0 * cos, (v + 1) as f32 / 100.0 * cos, 0.03 * cos];
            // float16 storage: 1e-3 relative.
            assert!(close(got, want, 1e-3), "l {l} v {v}: {got:?} vs {want:?}");
        }
    }
}

#[test]
fn every_texel_reads_its_own_index_whatever_the_size() {
    // From one texel to sizes that are neither powers of two nor multiples
    // of a cache line; random index bytes, so that rows, columns, views and
    // light groups all differ (the other tests' images are alike along
    // every column).
    let (dirs, _) = ring();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for s in [1usize, 5, 8, 13, 20] {
        let mut d = material(Interpolation::Default);
        let groups = d.groups();
        d.meta.resolution = s as u32;
        d.indices = (0..dirs.len() * s * s * groups).map(|_| rng.random_range(0..8u8)).collect();
        let m = Material::from_bytes(&d.to_bytes().unwrap()).unwrap();
        for (l, dl) in dirs.iter().enumerate() {
            for (v, dv) in dirs.iter().enumerate() {
                for t in 0..s * s {
                    let (x, y) = (t % s, t / s);
                    let uv = [(x as f32 + 0.5) / s as f32, (y as f32 + 0.5) / s as f32];
                    let got = m.eval(uv, f32v(*dl), f32v(*dv));
                    let i = d.indices[(v * s * s + t) * groups + d.light_groups[l] as usize];
                    let k = d.meta.colours as usize;
                    let want = d.palettes[(l * dirs.len() + v) * k + i as usize];
                    assert!(close(got, want, 1e-3), "S {s} l {l} v {v} texel ({x}, {y})");
                }
            }
        }
    }
}

#[test]
fn between_captured_directions_the_weights_are_barycentric_and_continuous() {
    let m = Material::from_bytes(&material(Interpolation::Default).to_bytes().unwrap()).unwrap();
    let (dirs, _) = ring();
    // Halfway (on the great circle) between view 1 and view 2, light at the zenith: the
    // green channel (view + 1)/100 mixes 2 and 3 equally.
    let mid: Vec<f64> = (0..3).map(|k| dirs[1][k] + dirs[2][k]).collect();
    let wo = [mid[0] as f32, mid[1] as f32, mid[2] as f32];
    let got = m.eval([0.5, 0.5], [0.0, 0.0, 1.0], wo);
    assert!((got[1] - 0.025).abs() < 1e-4, "{got:?}");
    // Continuity: a small step changes the answer by a small amount.
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..2000 {
        let d = random_dir(&mut rng, 75.0);
        let e = unit_f32([d[0] + 1e-4, d[1] - 1e-4, d[2]]);
        let (a, b) =
            (m.eval([0.4, 0.6], d, [0.0, 0.0, 1.0]), m.eval([0.4, 0.6], e, [0.0, 0.0, 1.0]));
        assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-3), "{d:?}: {a:?} vs {b:?}");
    }
}

fn unit_f32(d: [f32; 3]) -> [f32; 3] {
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    d.map(|x| x / l)
}

fn random_dir(rng: &mut ChaCha8Rng, max_theta_deg: f32) -> [f32; 3] {
    let t = rng.random::<f32>() * max_theta_deg.to_radians();
    let p = rng.random::<f32>() * std::f32::consts::TAU;
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

/// `n` queries at random uv in [0, 1)², directions within 80° of the normal.
fn random_queries(rng: &mut ChaCha8Rng, n: usize) -> Vec<ShadeQuery> {
    (0..n)
        .map(|_| ShadeQuery {
            uv: [rng.random(), rng.random()],
            wi: random_dir(rng, 80.0),
            wo: random_dir(rng, 80.0),
        })
        .collect()
}

#[test]
fn the_grid_finds_what_an_exhaustive_search_finds() {
    let (dirs, tris) = ring();
    let d32: Vec<[f32; 3]> = dirs.iter().map(|&d| f32v(d)).collect();
    let loc = locate::TriangleLocator::new(&d32, &tris, "t").unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..100_000 {
        let d = random_dir(&mut rng, 89.9);
        let (mut a, mut b) = ([(0, 0.0); 3], [(0, 0.0); 3]);
        loc.weights(d, &mut a);
        loc.weights_exhaustive(d, &mut b);
        let dense = |w: &locate::Weights3| {
            let mut v = [0f32; 7];
            for &(i, x) in w {
                v[i as usize] += x;
            }
            v
        };
        let (da, db) = (dense(&a), dense(&b));
        assert!((0..7).all(|i| (da[i] - db[i]).abs() < 1e-5), "{d:?}: {a:?} vs {b:?}");
    }
}

#[test]
fn beyond_the_outer_ring_clamps_and_below_the_horizon_is_black() {
    let m = Material::from_bytes(&material(Interpolation::Default).to_bytes().unwrap()).unwrap();
    let (dirs, _) = ring();
    // View along mirror 1's azimuth at 70°: the ring's vertex 1 (green 2/100), light at zenith.
    let t = 70f32.to_radians();
    let wo = [t.sin(), 0.0, t.cos()];
    let got = m.eval([0.5, 0.5], [0.0, 0.0, 1.0], wo);
    assert!((got[1] - 0.02).abs() < 1e-4, "{got:?}");
    // A light beyond the ring keeps the ring's f, times its own cos θi.
    let wi = [t.sin(), 0.0, t.cos()];
    let got = m.eval([0.5, 0.5], wi, [0.0, 0.0, 1.0]);
    let want_f = 2.0 / 100.0; // (l + 1)/100 · cos θ_l / cos θ_l for l = 1
    assert!((got[0] - want_f * t.cos()).abs() < 1e-4, "{got:?}");
    assert!(dirs[1][2] > 0.0);
    for (wi, wo) in [([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]), ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])] {
        assert_eq!(m.eval([0.5, 0.5], wi, wo), [0.0; 3]);
    }
    assert_eq!(m.eval([0.5, 0.5], [f32::NAN, 0.0, 1.0], [0.0, 0.0, 1.0]), [0.0; 3]);
    assert_eq!(m.eval([0.5, 0.5], [0.0; 3], [0.0, 0.0, 1.0]), [0.0; 3]);
    // Unnormalised directions are normalised.
    let a = m.eval([0.5, 0.5], [0.0, 0.0, 5.0], [0.0, 0.0, 0.5]);
    let b = m.eval([0.5, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]);
    assert_eq!(a, b);
    // Finite directions whose squares overflow or underflow f32 too; only
    // those shorter than 1e-6 are black.
    let (wi, wo) = ([0.3f32, -0.2, 0.9], [-0.4f32, 0.1, 0.8]);
    let want = m.eval([0.5, 0.5], wi, wo);
    assert!(want.iter().any(|&c| c > 0.0));
    for k in [1e30f32, 1e-10, 1e-20] {
        let got = m.eval([0.5, 0.5], wi.map(|c| c * k), wo.map(|c| c * k));
        let ok = if k > 1e-6 { close(got, want, 1e-6) } else { got == [0.0; 3] };
        assert!(ok, "scale {k}: {got:?} against {want:?}");
    }
    assert_eq!(m.eval([0.5, 0.5], [f32::INFINITY, 0.0, 1.0], wo), [0.0; 3]);
}

#[test]
fn uv_is_bilinear_and_wraps() {
    let m = Material::from_bytes(&material(Interpolation::Default).to_bytes().unwrap()).unwrap();
    let z = [0.0, 0.0, 1.0];
    // Blue = column/100: halfway between columns 2 and 3.
    let got = m.eval([3.0 / 8.0, 0.5], z, z);
    assert!((got[2] - 0.025).abs() < 1e-4, "{got:?}");
    // Clamped at the border, wrapped outside [0, 1).
    assert!((m.eval([0.01, 0.5], z, z)[2] - 0.0).abs() < 1e-6);
    assert_eq!(m.eval([1.0 + 3.0 / 8.0, -1.5], z, z), m.eval([3.0 / 8.0, 0.5], z, z));
}

#[test]
fn patent_cells_look_up_their_pairs() {
    let interp = Interpolation::Patent { columns: 64, rows: 16, points: 100 };
    let m = Material::from_bytes(&material(interp).to_bytes().unwrap()).unwrap();
    let (dirs, _) = ring();
    // Near a mirror's direction: its own image.
    for (v, dv) in dirs.iter().enumerate() {
        let got = m.eval([0.5, 0.5], [0.0, 0.0, 1.0], f32v(*dv));
        assert!((got[1] - (v + 1) as f32 / 100.0).abs() < 1e-4, "view {v}: {got:?}");
    }
}

#[test]
fn damaged_files_are_refused_without_panicking() {
    let good = material(Interpolation::Default).to_bytes().unwrap();
    // Every truncation.
    for n in (0..good.len()).step_by(7) {
        assert!(Material::from_bytes(&good[..n]).is_err(), "truncated at {n}");
    }
    // Flipped bytes anywhere: an error or a valid material, never a panic.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for _ in 0..300 {
        let mut b = good.clone();
        let i = rng.random_range(0..b.len());
        b[i] ^= 1 << rng.random_range(0..8);
        let _ = Material::from_bytes(&b);
    }
    // Specific refusals.
    let mut d = material(Interpolation::Default);
    d.indices[5] = 200;
    let e = d.to_bytes().unwrap_err().to_string();
    assert!(e.contains("outside the 8-colour palettes"), "{e}");
    let mut d = material(Interpolation::Default);
    d.palettes[3][1] = -1.0;
    assert!(d.to_bytes().unwrap_err().to_string().contains("finite radiance"));
    let mut d = material(Interpolation::Default);
    d.meta.views[2].direction = [0.0, 0.0, 2.0];
    assert!(d.to_bytes().unwrap_err().to_string().contains("not a unit vector"));
    let mut d = material(Interpolation::Default);
    if let DirectionTables::Triangles { views, .. } = &mut d.tables {
        views[0] = [0, 1, 9];
    }
    assert!(d.to_bytes().unwrap_err().to_string().contains("outside 0…6"));
    // More triangles than any triangulation of the directions has (they
    // would only make opening the file slow).
    let mut d = material(Interpolation::Default);
    if let DirectionTables::Triangles { views, .. } = &mut d.tables {
        let extra: Vec<[u16; 3]> = (0..11).map(|i| [0, 1 + i % 5, 2 + i % 5]).collect();
        *views = extra;
    }
    let e = Material::from_data(d).unwrap_err().to_string();
    assert!(
        e.contains("11 triangles over 7 directions: more than a triangulation has (10)"),
        "{e}"
    );
    let mut d = material(Interpolation::Default);
    d.meta.version = 7;
    assert!(d.to_bytes().unwrap_err().to_string().contains("version 7"));
    // The face the material was read on: kept through the file, refused
    // when it is no face.
    let mut d = material(Interpolation::Default);
    let face = crate::format::FaceRecord {
        height_mm: 0.2,
        slope: [0.035, -0.017],
        measured_on: "chroma".into(),
        sides_shown: true,
    };
    d.meta.provenance.face = Some(face.clone());
    let back = Material::from_bytes(&d.to_bytes().unwrap()).unwrap();
    assert_eq!(back.metadata().provenance.face, Some(face));
    d.meta.provenance.face.as_mut().unwrap().slope[0] = 3.0;
    let e = d.to_bytes().unwrap_err().to_string();
    assert!(e.contains("provenance.face: height 0.2 mm, slopes [3.0, -0.017]"), "{e}");
    let mut d = material(Interpolation::Default);
    d.light_groups[0] = 9;
    let e = d.to_bytes().unwrap_err().to_string();
    assert!(e.contains("× 10 (light groups 0…9)"), "{e}");
    // A safetensors file that is not a material.
    let other =
        safetensors::serialize(Vec::<(&str, safetensors::tensor::TensorView<'_>)>::new(), None)
            .unwrap();
    let e = Material::from_bytes(&other).unwrap_err().to_string();
    assert!(e.contains("not a material file"), "{e}");
    // Opened from a file, every refusal names the file once.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("other.material");
    std::fs::write(&path, &other).unwrap();
    let e = Material::open(&path).unwrap_err();
    let name = path.display().to_string();
    assert!(
        matches!(&e, MaterialError::File { path, source }
        if *path == name && matches!(**source, MaterialError::Metadata(_))),
        "{e:?}"
    );
    assert_eq!(e.to_string(), format!("{name}: {}", std::error::Error::source(&e).unwrap()));
    let e = Material::open(dir.path()).unwrap_err().to_string();
    assert_eq!(e, format!("{}: not a regular file", dir.path().display()));
}

#[test]
fn the_material_is_shareable_between_threads() {
    fn assert_sync<T: Send + Sync>() {}
    assert_sync::<Material>();
}

/// [`material`] with a texel model: texel column c has α 0.1 + 0.05 c, a
/// specular F0 0.5 and a normal tilted along u.
fn material_with_model() -> MaterialData {
    let mut d = material(Interpolation::Default);
    let s = d.meta.resolution as usize;
    d.meta.version = format::VERSION_TEXEL_MODEL;
    d.meta.texel_model = true;
    d.texels = (0..s * s)
        .map(|i| {
            let c = (i % s) as f32;
            let n = unit_f32([0.1, 0.02 * c, 1.0]);
            texel::TexelParams {
                diffuse: [0.2, 0.3, 0.4],
                specular: [0.5; 3],
                alpha: 0.1 + 0.05 * c,
                normal: n,
            }
        })
        .collect();
    d
}

#[test]
fn with_a_texel_model_captured_pairs_are_still_exact_and_the_rest_follows_the_model() {
    let data = material_with_model();
    let bytes = data.to_bytes().unwrap();
    let m = Material::from_bytes(&bytes).unwrap();
    assert!(m.metadata().texel_model);
    let (dirs, _) = ring();
    let uv = [3.5 / 8.0, 0.3];
    for (l, dl) in dirs.iter().enumerate() {
        for (v, dv) in dirs.iter().enumerate() {
            let got = m.eval(uv, f32v(*dl), f32v(*dv));
            let cos = dl[2] as f32;
            let want = [(l + 1) as f32 / 100.0 * cos, (v + 1) as f32 / 100.0 * cos, 0.03 * cos];
            assert!(close(got, want, 2e-3), "l {l} v {v}: {got:?} vs {want:?}");
        }
    }
    // Between captured pairs: the model's value plus the barycentric mix of
    // the residuals. With captured images equal to the model, eval is the
    // model everywhere.
    let mut d = material_with_model();
    let stored = Material::from_bytes(&d.to_bytes().unwrap()).unwrap();
    let (nl, nv, k) = (dirs.len(), dirs.len(), d.meta.colours as usize);
    // Palettes: the model at texel column c (all rows alike) and the pair.
    let texel_of = |c: usize| stored.texels[c];
    for l in 0..nl {
        for v in 0..nv {
            for c in 0..k {
                let p = texel::TexelParams::from_stored(&texel_of(c));
                d.palettes[(l * nv + v) * k + c] =
                    texel::reflected(&p, f32v(dirs[l]), f32v(dirs[v]));
            }
        }
    }
    let m = Material::from_bytes(&d.to_bytes().unwrap()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..200 {
        let (wi, wo) = (random_dir(&mut rng, 60.0), random_dir(&mut rng, 60.0));
        let c = rng.random_range(0..8);
        let uv = [(c as f32 + 0.5) / 8.0, rng.random::<f32>()];
        let p = texel::TexelParams::from_stored(&texel_of(c));
        let want = texel::reflected(&p, wi, wo);
        let got = m.eval(uv, wi, wo);
        // float16 palettes: the residuals are the rounding, ≤ 1e-3 relative.
        for ch in 0..3 {
            assert!(
                (got[ch] - want[ch]).abs() <= 2e-3 * want[ch].max(0.05),
                "{wi:?} {wo:?}: {got:?} vs {want:?}"
            );
        }
    }
}

#[test]
fn captured_pairs_come_back_under_a_steep_texel_model() {
    // A glossy model (α = 0.01) whose normal is tilted by about α from the
    // pairs whose light and view are mirror images: there its lobe is steep
    // and hundreds of times the stored value, so the model at the query's
    // directions must cancel the model at the captured pair's to the last
    // bits. Queries name the captured directions as the file does (f64),
    // or as their f32 casts.
    let mut data = material_with_model();
    let tilt = 0.6f32.to_radians();
    for t in &mut data.texels {
        t.alpha = 0.01;
        t.normal = [tilt.sin(), 0.0, tilt.cos()];
    }
    // The ring turned by 0.3 rad and the zenith moved off it: directions
    // whose f32 casts are not unit vectors to the last bit.
    let dirs: Vec<[f64; 3]> = ring()
        .0
        .iter()
        .map(|d| {
            let (c, s) = (0.3f64.cos(), 0.3f64.sin());
            let r = [c * d[0] - s * d[1] + 0.01, s * d[0] + c * d[1] - 0.02, d[2]];
            let n = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            r.map(|x| x / n)
        })
        .collect();
    assert!(dirs.iter().any(|&d| unit(f32v(d)) != Some(f32v(d))), "some casts renormalise");
    data.meta.lights = mirrors(&dirs);
    data.meta.views = mirrors(&dirs);
    let m = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
    let stored = texel::TexelParams::from_stored(&m.texels[3]);
    let uv = [3.5 / 8.0, 0.3];
    let mut steepest = 0.0f32;
    let palette_cos: Vec<f32> = ring().0.iter().map(|d| d[2] as f32).collect();
    for (l, dl) in dirs.iter().enumerate() {
        for (v, dv) in dirs.iter().enumerate() {
            let model = texel::reflected(&stored, f32v(*dl), f32v(*dv));
            steepest = steepest.max(model[0]);
            let cos = palette_cos[l];
            let want = [(l + 1) as f32 / 100.0 * cos, (v + 1) as f32 / 100.0 * cos, 0.03 * cos];
            // The file's directions cast to f32: the same bits as the
            // material's own, so the model cancels to f32's rounding of the
            // sums. Then renormalised or scaled: directions that differ in
            // the last bit, where the model itself moves by ≈ 10⁻⁵.
            for (wi, wo, rel) in [
                (f32v(*dl), f32v(*dv), 2e-6),
                (unit(f32v(*dl)).unwrap(), unit(f32v(*dv)).unwrap(), 5e-5),
                (f32v(dl.map(|x| 3.0 * x)), f32v(dv.map(|x| 0.25 * x)), 5e-5),
            ] {
                let got = m.eval(uv, wi, wo);
                for c in 0..3 {
                    // float16 palettes, then f32 sums against a model of up to ≈ 10³.
                    let tol = rel * model[c] + 1e-3 * want[c];
                    assert!(
                        (got[c] - want[c]).abs() <= tol,
                        "l {l} v {v} ({wi:?}, {wo:?}): {got:?} vs {want:?}, model {model:?}"
                    );
                }
            }
        }
    }
    assert!(steepest > 20.0, "a steep model at some captured pair: {steepest}");
}

/// The texel model in f64 as docs/material-format.md writes it.
fn model_f64(n: [f64; 3], a2: f64, wi: [f64; 3], wo: [f64; 3]) -> [f64; 3] {
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    // Unit in f64 (an f32 unit vector is one only to 10⁻⁷, which this
    // form's 1 − (n·h)² would feel at α = 0.003).
    let n = n.map(|x| x / dot(n, n).sqrt());
    let (ci, co) = (dot(n, wi), dot(n, wo));
    if wi[2] <= 0.0 || wo[2] <= 0.0 || ci <= 0.0 || co <= 0.0 {
        return [0.0; 3];
    }
    let hs = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
    let l = dot(hs, hs).sqrt();
    let h = hs.map(|x| x / l);
    let nh = dot(n, h);
    let d = a2 / (std::f64::consts::PI * (nh * nh * (a2 - 1.0) + 1.0).powi(2));
    let lambda = |c: f64| ((1.0 + a2 * (1.0 - c * c) / (c * c)).sqrt() - 1.0) / 2.0;
    let g = 1.0 / (1.0 + lambda(ci) + lambda(co));
    let s = (1.0 - dot(wi, h)).powi(5);
    let common = d * g / (4.0 * co);
    [ci / std::f64::consts::PI, common * (1.0 - s), common * s]
}

#[test]
fn the_texel_model_keeps_f32_precision_at_a_narrow_lobe() {
    // Pairs around the lobe's peak and on its flank, for narrow and wide
    // lobes: f32 against f64 at the same (f32) inputs. The textbook form
    // of D lost ≈ 10⁻³ of its value at α = 0.01 near the peak.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for alpha in [0.003f32, 0.01, 0.05, 0.3] {
        let mut worst = 0.0f64;
        for _ in 0..2000 {
            let n = unit(f32v(random_dir(&mut rng, 30.0).map(f64::from))).unwrap();
            let wi = random_dir(&mut rng, 70.0);
            // wo: wi mirrored about n, then moved by up to 3 α.
            let k = 2.0 * (n[0] * wi[0] + n[1] * wi[1] + n[2] * wi[2]);
            let r = [k * n[0] - wi[0], k * n[1] - wi[1], k * n[2] - wi[2]];
            let j = [0, 1, 2].map(|_| rng.random_range(-3.0..3.0) * alpha);
            let Some(wo) = unit([r[0] + j[0], r[1] + j[1], r[2] + j[2]]) else { continue };
            let a2 = alpha * alpha;
            let got = texel::terms(n, a2, wi, wo);
            let want =
                model_f64(n.map(f64::from), f64::from(a2), wi.map(f64::from), wo.map(f64::from));
            if want == [0.0; 3] || got == [0.0; 3] {
                assert_eq!(got == [0.0; 3], want == [0.0; 3], "{alpha} {n:?} {wi:?} {wo:?}");
                continue;
            }
            for c in 0..3 {
                let e = (f64::from(got[c]) - want[c]).abs() / want[c].abs().max(1e-30);
                // Fresnel's term is (1 − wi·h)⁵ · D G / 4co: near normal
                // incidence it is tiny and keeps only f32's absolute precision.
                if c < 2 || want[2] > 1e-6 * want[1] {
                    worst = worst.max(e);
                }
            }
        }
        // f32's rounding of h alone moves it by ≈ 10⁻⁷ rad, which the lobe
        // feels as ≈ 10⁻⁷ / α; the rest is the evaluation's.
        let bound = 1e-5 + 2e-7 / f64::from(alpha);
        assert!(worst < bound, "α {alpha}: worst relative error {worst:e} (bound {bound:e})");
    }
}

#[test]
fn bad_texel_models_are_refused() {
    let e = |d: MaterialData| d.to_bytes().unwrap_err().to_string();
    let mut d = material_with_model();
    d.texels[9].alpha = 0.0;
    assert!(e(d).contains("texel_model: texel (1, 1): α 0"), "α");
    let mut d = material_with_model();
    d.texels[2].specular[1] = 1.5;
    assert!(e(d).contains("outside [0, 1]"));
    let mut d = material_with_model();
    d.texels[3].normal = [0.9, 0.5, 0.1];
    assert!(e(d).contains("not above the sample"));
    let mut d = material_with_model();
    d.texels[3].diffuse[0] = f32::NAN;
    assert!(e(d).contains("outside [0, 1]"));
    // Version and flag must agree; the patent's interpolation has no model.
    let mut d = material_with_model();
    d.meta.version = format::VERSION;
    assert!(e(d).contains("texel model is version 2"));
    let mut d = material(Interpolation::Default);
    d.meta.version = format::VERSION_TEXEL_MODEL;
    assert!(e(d).contains("version 2 without a texel model"));
    let mut d = material_with_model();
    d.texels.pop();
    assert!(e(d).contains("texel_model"));
    // A version-1 file does not mention the model at all.
    let v1 = material(Interpolation::Default).to_bytes().unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&v1).unwrap();
    assert!(!header.metadata().as_ref().unwrap()[format::METADATA_KEY].contains("texel"));
    // Damage anywhere in a version-2 file: an error or a material, never a panic.
    damage_never_panics(&material_with_model().to_bytes().unwrap(), 11);
}

/// 300 single-bit flips anywhere in `good`: each refused for its content
/// digest. Then 300 in `good` without its digest (a file written before
/// the digest, or one whose digest was recomputed): each an error or a
/// material that shades finite values ≥ 0, never a panic.
fn damage_never_panics(good: &[u8], seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut flipped = |bytes: &[u8]| {
        let mut b = bytes.to_vec();
        let i = rng.random_range(0..b.len());
        b[i] ^= 1 << rng.random_range(0..8);
        b
    };
    for _ in 0..300 {
        assert!(Material::from_bytes(&flipped(good)).is_err());
    }
    let bare = without_digest(good);
    for _ in 0..300 {
        if let Ok(m) = Material::from_bytes(&flipped(&bare)) {
            let v = m.eval([0.3, 0.6], [0.1, 0.2, 0.97], [-0.3, 0.1, 0.95]);
            assert!(v.iter().all(|x| x.is_finite() && *x >= 0.0), "{v:?}");
        }
    }
}

/// `bytes`, a material file with a content digest, written again without it.
fn without_digest(bytes: &[u8]) -> Vec<u8> {
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes).unwrap();
    assert!(header.metadata().as_ref().unwrap().contains_key(format::DIGEST_KEY));
    let bare = format::without_digest(bytes).unwrap();
    Material::from_bytes(&bare).expect("a file without a digest reads");
    bare
}

#[test]
fn the_content_digest_covers_every_byte_a_reader_uses() {
    // The file's digest is its content's; a changed palette value, a
    // metadata value or two tensors' names swapped (both [63, 3] U16) are
    // refused with the reason; the digest does not depend on the header's
    // key order.
    let good = material(Interpolation::Default).to_bytes().unwrap();
    let (n, header) = safetensors::SafeTensors::read_metadata(&good).unwrap();
    let meta = header.metadata().clone().unwrap();
    assert_eq!(meta[format::DIGEST_KEY], format::content_digest(&good).unwrap());
    assert_eq!(meta[format::DIGEST_KEY].len(), 64);
    let refused = |b: &[u8]| match Material::from_bytes(b) {
        Err(MaterialError::Container(e)) => assert!(e.contains("altered or damaged"), "{e}"),
        other => panic!("{:?}", other.map(|_| ())),
    };
    let mut b = good.clone();
    let last = b.len() - 1;
    b[last] ^= 0x01;
    refused(&b);
    let text = std::str::from_utf8(&good[8..8 + n]).unwrap().to_string();
    let swap = |t: &str, a: &str, z: &str| t.replace(a, "\u{1}").replace(z, a).replace("\u{1}", z);
    for altered in [
        text.replacen(r#"half_vector_shift\":1.0"#, r#"half_vector_shift\":0.5"#, 1),
        swap(&text, "view_triangles", "light_triangles"),
    ] {
        assert_ne!(altered, text);
        let mut b = good[..8].to_vec();
        b.extend_from_slice(altered.as_bytes());
        b.extend_from_slice(&good[8 + n..]);
        refused(&b);
    }
    // Written again (each time with a new hash map of metadata), the same
    // bytes: the header's keys are sorted.
    for _ in 0..8 {
        assert!(material(Interpolation::Default).to_bytes().unwrap() == good);
    }
    // The same content with its header's keys in another order.
    let st = safetensors::SafeTensors::deserialize(&good).unwrap();
    let mut tensors = st.tensors();
    tensors.reverse();
    let again = safetensors::serialize(tensors, Some(meta.clone())).unwrap();
    Material::from_bytes(&again).expect("the same content");
    // A metadata key the format does not name (a flip in the digest's) is
    // refused.
    let mut other = meta;
    let digest = other.remove(format::DIGEST_KEY).unwrap();
    other.insert("content_sha257".to_string(), digest);
    let renamed = safetensors::serialize(st.tensors(), Some(other)).unwrap();
    match Material::from_bytes(&renamed) {
        Err(MaterialError::Metadata(e)) => assert!(e.contains("content_sha257"), "{e}"),
        other => panic!("{:?}", other.map(|_| ())),
    }
}

/// The default interpolation's test materials, without and with a texel
/// model, their index images random so that every texel and pair differs.
fn scrambled(rng: &mut ChaCha8Rng) -> [Material; 2] {
    [material(Interpolation::Default), material_with_model()].map(|mut d| {
        let k = d.meta.colours;
        for i in &mut d.indices {
            *i = rng.random_range(0..k) as u8;
        }
        Material::from_data(d).unwrap()
    })
}

/// Asserts that `eval_batch` answers every query exactly as `eval` does;
/// how many answers are lit.
fn batch_as_eval(m: &Material, queries: &[ShadeQuery]) -> usize {
    let mut out = vec![[f32::NAN; 3]; queries.len()];
    m.eval_batch(queries, &mut out);
    let mut lit = 0;
    for (q, o) in queries.iter().zip(&out) {
        assert_eq!(*o, m.eval(q.uv, q.wi, q.wo), "{q:?}");
        lit += o.iter().any(|&c| c > 0.0) as usize;
    }
    lit
}

#[test]
fn a_batch_answers_each_query_as_eval_does() {
    // Random indices, so every texel and pair differs; 100 queries (not a
    // multiple of the block) with black ones among them.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for m in scrambled(&mut rng) {
        let queries: Vec<ShadeQuery> = (0..100)
            .map(|i| ShadeQuery {
                uv: [rng.random::<f32>() * 3.0 - 1.0, rng.random()],
                wi: match i % 17 {
                    3 => [f32::NAN, 0.0, 1.0],
                    5 => [0.3, 0.1, -0.2],
                    _ => random_dir(&mut rng, 89.0),
                },
                wo: if i % 23 == 7 { [0.0; 3] } else { random_dir(&mut rng, 89.0) },
            })
            .collect();
        let lit = batch_as_eval(&m, &queries);
        // 17 black by construction; the model may clamp a few more to 0.
        assert!(lit >= 60, "{lit} of 100 lit");
    }
}

#[test]
fn a_batch_reuses_a_lookup_only_for_the_same_directions() {
    // Runs of queries sharing their directions (as an image under one light
    // and view does), runs that differ in wi only, in wo only or by one
    // bit, black directions repeated and a NaN uv inside a run: every
    // answer as `eval`'s.
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    for m in scrambled(&mut rng) {
        let mut queries = Vec::new();
        let (mut wi, mut wo) = (random_dir(&mut rng, 80.0), random_dir(&mut rng, 80.0));
        for run in 0..60 {
            match run % 6 {
                0 => wi = random_dir(&mut rng, 80.0),
                1 => wo = random_dir(&mut rng, 80.0),
                2 => wi[0] = f32::from_bits(wi[0].to_bits() ^ 1),
                3 => wo = [0.3, 0.1, -0.2],
                4 => wi = [f32::NAN, 0.0, 1.0],
                _ => (wi, wo) = (random_dir(&mut rng, 80.0), random_dir(&mut rng, 80.0)),
            }
            for i in 0..rng.random_range(1..7) {
                let u = if run % 5 == 2 && i == 1 { f32::NAN } else { rng.random() };
                queries.push(ShadeQuery { uv: [u, rng.random()], wi, wo });
            }
        }
        let lit = batch_as_eval(&m, &queries);
        assert!(lit > queries.len() / 3, "{lit} of {} lit", queries.len());
    }
}

/// Counts the allocations of the thread that makes them, so that tests
/// running beside one another on other threads do not disturb the count.
struct CountingAllocator;

thread_local! {
    static ALLOCATIONS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

// SAFETY: every call is forwarded to the system allocator unchanged; the
// count is a const-initialised thread-local `Cell` without a destructor,
// which never allocates and is usable for the thread's whole life.
unsafe impl std::alloc::GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's contract, passed on.
        unsafe { std::alloc::System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's contract, passed on.
        unsafe { std::alloc::System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new: usize) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's contract, passed on.
        unsafe { std::alloc::System.realloc(ptr, layout, new) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: the caller's contract, passed on.
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static COUNTING: CountingAllocator = CountingAllocator;

fn allocations() -> usize {
    ALLOCATIONS.with(|c| c.get())
}

#[test]
fn no_query_allocates() {
    // The crate documentation promises it: a renderer calls `eval` from its
    // inner loop on many threads.
    let before = allocations();
    std::hint::black_box(Vec::<u8>::with_capacity(16));
    assert_eq!(allocations(), before + 1, "the counter counts this thread's allocations");
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let patent = Interpolation::Patent { columns: 16, rows: 4, points: 10 };
    for d in [material(Interpolation::Default), material_with_model(), material(patent)] {
        let m = Material::from_data(d).unwrap();
        m.prepare_importance();
        // Inside the ring, beyond it, at a captured direction, below the
        // horizon, NaN, zero and huge vectors, uv far outside [0, 1].
        let queries: Vec<ShadeQuery> = (0..300)
            .map(|i| ShadeQuery {
                uv: [rng.random::<f32>() * 50.0 - 25.0, rng.random()],
                wi: match i % 7 {
                    1 => [f32::NAN, 0.0, 1.0],
                    2 => [0.3, 0.1, -0.2],
                    3 => [0.0, 0.0, 1.0],
                    4 => [1e30, 0.0, 1e30],
                    _ => random_dir(&mut rng, 89.0),
                },
                wo: if i % 11 == 5 { [0.0; 3] } else { random_dir(&mut rng, 89.0) },
            })
            .collect();
        let mut out = vec![[0.0f32; 3]; queries.len()];
        let mut sum = 0.0f32;
        let before = allocations();
        m.eval_batch(&queries, &mut out);
        for q in &queries {
            sum += m.eval(q.uv, q.wi, q.wo)[0];
            sum += m.pdf(q.uv, q.wi, q.wo);
            if let Some(s) = m.sample(q.uv, q.wo, q.uv[1], [q.wi[0].abs(), q.wi[1].abs()]) {
                sum += s.pdf;
            }
        }
        let made = allocations() - before;
        assert_eq!(
            made,
            0,
            "{made} allocations in 1 500 queries ({:?})",
            m.metadata().interpolation
        );
        assert!(sum > 0.0 && out.iter().any(|o| o[0] > 0.0), "the queries shade something");
    }
}

/// `d` with a detail layer (version 3): factors 2^((x + 2y) mod 5 − 2)/2
/// over its 2S × 2S grid, ⅓…1.4 (within ¼…4), differing per channel.
fn with_detail(mut d: MaterialData) -> MaterialData {
    let f = 2 * d.meta.resolution as usize;
    d.meta.version = format::VERSION_DETAIL;
    d.meta.detail = true;
    d.detail = (0..f * f)
        .map(|t| {
            let (x, y) = (t % f, t / f);
            std::array::from_fn(|c| 2f32.powf((((x + 2 * y + c) % 5) as f32 - 2.0) / 2.0))
        })
        .collect();
    d
}

/// A material file's bytes with its metadata JSON edited by `edit`, the
/// tensors as they were.
fn with_metadata(bytes: &[u8], edit: impl Fn(&str) -> String) -> Vec<u8> {
    let st = safetensors::SafeTensors::deserialize(bytes).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes).unwrap();
    let json = edit(&header.metadata().as_ref().unwrap()[format::METADATA_KEY]);
    let tensors: Vec<(String, safetensors::tensor::TensorView<'_>)> =
        st.tensors().into_iter().collect();
    let info = std::collections::HashMap::from([(format::METADATA_KEY.to_string(), json)]);
    safetensors::serialize(tensors, Some(info)).unwrap()
}

#[test]
fn a_detail_layer_multiplies_every_answer() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    for base in [
        material(Interpolation::Default),
        material_with_model(),
        material(Interpolation::Patent { columns: 24, rows: 6, points: 10 }),
    ] {
        let detailed = with_detail(base.clone());
        let layer = detailed.detail.clone();
        let (plain, detailed) = (
            Material::from_bytes(&base.to_bytes().unwrap()).unwrap(),
            Material::from_bytes(&detailed.to_bytes().unwrap()).unwrap(),
        );
        let f = 16usize;
        for _ in 0..200 {
            // At a 2S texel centre (there the layer's own value), uv also
            // wrapped by a whole turn.
            let (x, y) = (rng.random_range(0..f), rng.random_range(0..f));
            let uv = [(x as f32 + 0.5) / f as f32, (y as f32 + 0.5) / f as f32];
            let (wi, wo) = (random_dir(&mut rng, 60.0), random_dir(&mut rng, 60.0));
            let (a, b) = (plain.eval(uv, wi, wo), detailed.eval([uv[0] + 1.0, uv[1]], wi, wo));
            let want: [f32; 3] = std::array::from_fn(|c| a[c] * layer[y * f + x][c]);
            assert!(close(b, want, 1e-3), "{b:?} against {want:?} at {uv:?}");
        }
        // Halfway between two 2S texel centres along u: their mean.
        let (wi, wo) = ([0.1, 0.2, 0.97], [-0.3, 0.1, 0.95]);
        let uv = [3.0 / f as f32, 5.5 / f as f32];
        let (a, b) = (plain.eval(uv, wi, wo), detailed.eval(uv, wi, wo));
        for c in 0..3 {
            let m = 0.5 * (layer[5 * f + 2][c] + layer[5 * f + 3][c]);
            assert!((b[c] - a[c] * m).abs() <= 1e-3 * b[c].abs().max(1e-3), "{c}");
        }
        // The batch answers as `eval` does.
        assert!(batch_as_eval(&detailed, &random_queries(&mut rng, 500)) > 0);
    }
}

#[test]
fn bad_detail_layers_are_refused() {
    let e = |d: MaterialData| d.to_bytes().unwrap_err().to_string();
    for (bad, what) in [(5.0, "factor 5"), (0.1, "factor 0.0999"), (f32::NAN, "factor NaN")] {
        let mut d = with_detail(material(Interpolation::Default));
        d.detail[37][1] = bad;
        let msg = e(d);
        assert!(msg.contains(what) && msg.contains("(5, 2)"), "{msg}");
    }
    let mut d = with_detail(material(Interpolation::Default));
    d.detail.pop();
    assert!(e(d).contains("detail: 255 factors for 16 × 16"));
    // Version and flag must agree, both ways.
    let mut d = with_detail(material(Interpolation::Default));
    d.meta.version = format::VERSION_TEXEL_MODEL;
    assert!(e(d).contains("a detail layer is versions 3 and 4's"));
    let mut d = material(Interpolation::Default);
    d.meta.version = format::VERSION_DETAIL;
    assert!(e(d).contains("version 3 without a detail layer"));
    // A layer the metadata does not announce is an unexpected tensor.
    let good = with_detail(material(Interpolation::Default)).to_bytes().unwrap();
    let bytes = with_metadata(&good, |json| {
        json.replace("\"detail\":true", "")
            .replace(",}", "}")
            .replace("\"version\":3", "\"version\":1")
    });
    let msg = Material::from_bytes(&bytes).unwrap_err().to_string();
    assert!(msg.contains("unexpected tensor `detail`"), "{msg}");
    // Damage anywhere in a version-3 file: an error or a material, never a panic.
    damage_never_panics(&good, 12);
}

#[test]
fn light_groups_may_differ_in_size() {
    // Seven lights in three groups (3, 2, 2) instead of ⌈7 / 2⌉ = 4.
    let regroup = |groups: &[u8], g: u32| {
        let mut d = material(Interpolation::Default);
        let (n, s) = (d.meta.lights.len(), d.meta.resolution as usize);
        let count = groups.iter().map(|&x| x as usize + 1).max().unwrap();
        d.meta.lights_per_index = g;
        d.light_groups = groups.to_vec();
        d.indices = (0..n * s * s * count).map(|i| ((i / count) % s) as u8).collect();
        d
    };
    let d = regroup(&[0, 0, 0, 1, 1, 2, 2], 3);
    let m = Material::from_bytes(&d.to_bytes().unwrap()).unwrap();
    let (dirs, _) = ring();
    for (l, dl) in dirs.iter().enumerate() {
        let got = m.eval([3.5 / 8.0, 0.3], f32v(*dl), f32v(dirs[2]));
        let cos = dl[2] as f32;
        let want = [(l + 1) as f32 / 100.0 * cos, 0.03 * cos, 0.03 * cos];
        assert!(close(got, want, 1e-3), "light {l}: {got:?} against {want:?}");
    }
    let e = |d: MaterialData| d.to_bytes().unwrap_err().to_string();
    // A group without a light, more lights in one than g, more groups than lights.
    assert!(e(regroup(&[0, 0, 0, 2, 2, 3, 3], 3)).contains("group 1 of 4 holds no light"));
    assert!(e(regroup(&[0, 0, 0, 1, 1, 2, 2], 2)).contains("3 light groups for 7 lights"));
    let mut d = regroup(&[0, 1, 2, 3, 4, 5, 6], 1);
    d.indices.extend(std::iter::repeat_n(0, 7 * 64));
    d.light_groups[6] = 7;
    assert!(e(d).contains("light groups for 7 lights"));
}

/// `d` with a detail layer (version 4) of two light components: component
/// r at 2S texel (x, y) is sin(0.7 (r + 1) x + 0.3 y + c) per channel c,
/// light l's coefficients (0.1 (l − 3), 0.05 l − 0.1).
fn with_light_detail(d: MaterialData) -> MaterialData {
    let mut d = with_detail(d);
    let (f, nl) = (2 * d.meta.resolution as usize, d.meta.lights.len());
    d.meta.version = format::VERSION_LIGHT_DETAIL;
    d.meta.detail_components = 2;
    d.detail_bases = (0..2 * f * f)
        .map(|i| {
            let (r, t) = (i / (f * f), i % (f * f));
            let (x, y) = ((t % f) as f32, (t / f) as f32);
            std::array::from_fn(|c| (0.7 * (r + 1) as f32 * x + 0.3 * y + c as f32).sin())
        })
        .collect();
    d.detail_coefficients =
        (0..nl).flat_map(|l| [0.1 * (l as f32 - 3.0), 0.05 * l as f32 - 0.1]).collect();
    d
}

#[test]
fn light_components_follow_the_light() {
    let base = material(Interpolation::Default);
    let d = with_light_detail(base.clone());
    let f = 16usize;
    let (plain, lit) = (
        Material::from_bytes(&base.to_bytes().unwrap()).unwrap(),
        Material::from_bytes(&d.to_bytes().unwrap()).unwrap(),
    );
    let (dirs, _) = ring();
    // At every captured light, at 2S texel centres: the shared factor times
    // e^(Σ c_lr B_r), clamped to the layer's range.
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    for (l, dl) in dirs.iter().enumerate() {
        for _ in 0..20 {
            let (x, y) = (rng.random_range(0..f), rng.random_range(0..f));
            let t = y * f + x;
            let uv = [(x as f32 + 0.5) / f as f32, (y as f32 + 0.5) / f as f32];
            let wo = f32v(dirs[rng.random_range(0..dirs.len())]);
            let (a, b) = (plain.eval(uv, f32v(*dl), wo), lit.eval(uv, f32v(*dl), wo));
            let want: [f32; 3] = std::array::from_fn(|c| {
                let log = d.detail_coefficients[2 * l] * d.detail_bases[t][c]
                    + d.detail_coefficients[2 * l + 1] * d.detail_bases[f * f + t][c];
                a[c] * (d.detail[t][c] * log.exp()).clamp(0.25, 4.0)
            });
            assert!(close(b, want, 2e-3), "light {l} at {uv:?}: {b:?} against {want:?}");
        }
    }
    // Between lights, continuous: a small step of wi changes the answer by
    // a small amount.
    for _ in 0..2000 {
        let wi = random_dir(&mut rng, 75.0);
        let e = unit_f32([wi[0] + 1e-4, wi[1] - 1e-4, wi[2]]);
        let (a, b) =
            (lit.eval([0.4, 0.6], wi, [0.0, 0.0, 1.0]), lit.eval([0.4, 0.6], e, [0.0, 0.0, 1.0]));
        assert!((0..3).all(|k| (a[k] - b[k]).abs() < 2e-3), "{wi:?}: {a:?} vs {b:?}");
    }
    // The lights differ: at a 2S texel centre, seen from the zenith, lights
    // 0 and 6 (coefficients (−0.3, −0.1) and (0.3, 0.2)) give two factors.
    let uv = [3.5 / f as f32, 9.5 / f as f32];
    let ratio = |l: usize| {
        let (a, b) = (
            plain.eval(uv, f32v(dirs[l]), f32v(dirs[0])),
            lit.eval(uv, f32v(dirs[l]), f32v(dirs[0])),
        );
        b[0] / a[0]
    };
    let b = |r: usize| d.detail_bases[r * f * f + 9 * f + 3][0];
    let want = |l: usize| {
        let c = &d.detail_coefficients[2 * l..];
        d.detail[9 * f + 3][0] * (c[0] * b(0) + c[1] * b(1)).exp()
    };
    assert!((want(0) / want(6) - 1.0).abs() > 0.2, "a test point where the lights differ");
    for l in [0, 6] {
        assert!((ratio(l) - want(l)).abs() < 2e-3 * want(l), "light {l}: {}", ratio(l));
    }
    // The batch answers as `eval` does, with the patent's tables too.
    let queries = random_queries(&mut rng, 500);
    assert!(batch_as_eval(&lit, &queries) > 0);
    for base in [
        material_with_model(),
        material(Interpolation::Patent { columns: 24, rows: 6, points: 10 }),
    ] {
        let m = Material::from_bytes(&with_light_detail(base).to_bytes().unwrap()).unwrap();
        assert!(batch_as_eval(&m, &queries) > 0);
    }
}

#[test]
fn bad_light_components_are_refused() {
    let e = |d: MaterialData| match d.to_bytes() {
        Ok(_) => "accepted".to_string(),
        Err(e) => e.to_string(),
    };
    let good = || with_light_detail(material(Interpolation::Default));
    let mut d = good();
    d.detail_bases[16 * 16 + 37][2] = 1.5;
    let msg = e(d);
    assert!(msg.contains("detail_bases: 1.5 at component 1, (5, 2) outside −1…1"), "{msg}");
    for (bad, what) in
        [(100.0, "100 of light 3"), (f32::NAN, "NaN of light 3"), (f32::INFINITY, "inf of light 3")]
    {
        let mut d = good();
        d.detail_coefficients[7] = bad;
        let msg = e(d);
        assert!(msg.contains(&format!("detail_coefficients: {what} outside −64…64")), "{msg}");
    }
    let mut d = good();
    d.detail_coefficients.pop();
    assert!(e(d).contains("detail components: 512 basis values and 13 coefficients"));
    // Version and components must agree, both ways; at most eight.
    let mut d = good();
    d.meta.version = format::VERSION_DETAIL;
    assert!(e(d).contains("version 3 with 2 light components"));
    let mut d = with_detail(material(Interpolation::Default));
    d.meta.version = format::VERSION_LIGHT_DETAIL;
    assert!(e(d).contains("version 4 with 0 light components"));
    let mut d = good();
    let f2 = 16 * 16;
    d.meta.detail_components = 9;
    d.detail_bases = (0..9 * f2).map(|i| d.detail_bases[i % (2 * f2)]).collect();
    d.detail_coefficients = vec![0.1; 7 * 9];
    let msg = e(d);
    assert!(msg.contains("detail_components 9 outside 0…8"), "{msg}");
    // Components the metadata does not announce are unexpected tensors.
    let bytes = good().to_bytes().unwrap();
    let stripped = with_metadata(&bytes, |json| {
        json.replace(",\"detail_components\":2", "").replace("\"version\":4", "\"version\":3")
    });
    let msg = Material::from_bytes(&stripped).unwrap_err().to_string();
    assert!(msg.contains("unexpected tensor `detail_"), "{msg}");
    // Damage anywhere in a version-4 file: an error or a material, never a panic.
    damage_never_panics(&bytes, 13);
}

#[test]
fn palette_colours_beyond_float16_are_stored_at_its_largest() {
    // A near-mirror's highlight measured above float16's largest value: the
    // file is written and read, the colour at 65 504, the rest exact.
    let mut d = material(Interpolation::Default);
    d.palettes[3] = [1.0e6, 7.0e4, 1.0];
    assert_eq!(d.palettes_beyond_float16(), 2);
    let back = MaterialData::from_bytes(&d.to_bytes().unwrap()).unwrap();
    assert_eq!(back.palettes[3], [format::PALETTE_MAX, format::PALETTE_MAX, 1.0]);
    let f16 = |x: f32| half::f16::from_f32(x).to_f32();
    assert_eq!(back.palettes[4], d.palettes[4].map(f16));
    assert_eq!(back.palettes_beyond_float16(), 0);
}

#[test]
fn the_concentric_map_round_trips() {
    use importance::{disk_to_square, square_to_disk};
    let n = 101;
    for i in 0..n {
        for j in 0..n {
            let p = [i as f32 / (n - 1) as f32, j as f32 / (n - 1) as f32];
            let d = square_to_disk(p);
            assert!(d[0] * d[0] + d[1] * d[1] <= 1.0 + 1e-6, "{p:?} → {d:?}");
            let q = disk_to_square(d);
            assert!(
                (q[0] - p[0]).abs() < 2e-6 && (q[1] - p[1]).abs() < 2e-6,
                "{p:?} → {d:?} → {q:?}"
            );
        }
    }
}

/// The directions of a (θ, φ) grid of `nt` × `nphi` bins, each split
/// into `sub` × `sub` patches, at a seeded random point of each patch, with
/// the patch's solid angle: (bin, direction, dω). Random points, not
/// midpoints: the pdf is constant on cells whose edges cross the grid, and
/// midpoints integrate that with an error of one sign.
fn hemisphere_grid(
    nt: usize,
    nphi: usize,
    sub: usize,
) -> impl Iterator<Item = (usize, [f32; 3], f32)> {
    let dt = std::f64::consts::FRAC_PI_2 / (nt * sub) as f64;
    let dphi = std::f64::consts::TAU / (nphi * sub) as f64;
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    (0..nt * sub).flat_map(move |a| (0..nphi * sub).map(move |b| (a, b))).map(move |(a, b)| {
        let (t0, p) = (a as f64 * dt, (b as f64 + rng.random::<f64>()) * dphi);
        // Uniform in cos θ within the patch: its solid angle is then exact.
        let z = t0.cos() - rng.random::<f64>() * (t0.cos() - (t0 + dt).cos());
        let s = (1.0 - z * z).sqrt();
        let d = [s * p.cos(), s * p.sin(), z].map(|x| x as f32);
        ((a / sub) * nphi + b / sub, d, ((t0.cos() - (t0 + dt).cos()) * dphi) as f32)
    })
}

/// The (θ, φ) bin of a direction above the horizon.
fn hemisphere_bin(d: [f32; 3], nt: usize, nphi: usize) -> usize {
    let t = d[2].clamp(-1.0, 1.0).acos() / std::f32::consts::FRAC_PI_2;
    let a = ((t * nt as f32) as usize).min(nt - 1);
    let phi = d[1].atan2(d[0]).rem_euclid(std::f32::consts::TAU);
    let b = ((phi / std::f32::consts::TAU * nphi as f32) as usize).min(nphi - 1);
    a * nphi + b
}

/// Pearson's χ² of observed against expected counts, bins expecting fewer
/// than 5 pooled, as Wilson and Hilferty's normal deviate.
fn chi_square_z(observed: &[f64], expected: &[f64]) -> f64 {
    let (mut chi, mut bins, mut po, mut pe) = (0.0, 0usize, 0.0, 0.0);
    for (o, e) in observed.iter().zip(expected) {
        if *e < 5.0 {
            (po, pe) = (po + o, pe + e);
        } else {
            chi += (o - e) * (o - e) / e;
            bins += 1;
        }
    }
    if pe >= 5.0 {
        chi += (po - pe) * (po - pe) / pe;
        bins += 1;
    } else {
        assert!(po <= 20.0, "{po} samples where {pe} were expected");
    }
    let k = (bins - 1) as f64;
    ((chi / k).powf(1.0 / 3.0) - (1.0 - 2.0 / (9.0 * k))) / (2.0 / (9.0 * k)).sqrt()
}

#[test]
fn samples_follow_their_pdf() {
    // Pearson's test of 100 000 draws against the pdf integrated over
    // 16 × 32 bins in (θ, φ), plus one for the draws below the horizon.
    let (nz, nphi, n) = (16, 32, 100_000);
    let patent = Interpolation::Patent { columns: 16, rows: 4, points: 10 };
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for (name, d) in [
        ("texel model", material_with_model()),
        ("default", material(Interpolation::Default)),
        ("patent", material(patent)),
    ] {
        let m = Material::from_data(d).unwrap();
        for (uv, wo) in [
            ([0.3, 0.6], [0.0, 0.0, 1.0]),
            ([0.9, 0.1], unit_f32([0.5, 0.2, 0.8])),
            ([0.05, 0.5], unit_f32([-0.9, 0.3, 0.3])),
        ] {
            let mut expected = vec![0.0f64; nz * nphi + 1];
            let mut total = 0.0f64;
            for (bin, wi, dw) in hemisphere_grid(nz, nphi, 24) {
                let p = (m.pdf(uv, wi, wo) * dw) as f64;
                expected[bin] += p * n as f64;
                total += p;
            }
            assert!(total <= 1.002, "{name} {wo:?}: the pdf integrates to {total}");
            assert!(total > 0.5, "{name} {wo:?}: only {total} above the horizon");
            expected[nz * nphi] = (1.0 - total).max(0.0) * n as f64;
            let mut observed = vec![0.0f64; nz * nphi + 1];
            for _ in 0..n {
                match m.sample(uv, wo, rng.random(), [rng.random(), rng.random()]) {
                    Some(s) => {
                        assert!(s.wi[2] > 0.0 && (dot3(s.wi, s.wi) - 1.0).abs() < 1e-5, "{s:?}");
                        assert_eq!(s.pdf, m.pdf(uv, s.wi, wo), "{name} {wo:?}: {s:?}");
                        assert_eq!(s.f_cos, m.eval(uv, s.wi, wo), "{name} {wo:?}: {s:?}");
                        observed[hemisphere_bin(s.wi, nz, nphi)] += 1.0;
                    }
                    None => observed[nz * nphi] += 1.0,
                }
            }
            let z = chi_square_z(&observed, &expected);
            assert!(z < 4.0, "{name} {wo:?}: χ² deviate {z:.2}");
        }
    }
}

fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[test]
fn importance_sampling_is_unbiased_and_beats_cosine_sampling() {
    // ∫ f cos θi dωi at one uv and wo: by quadrature, by the material's
    // samples and by cosine-weighted ones, 20 000 each. The test material's
    // lobe widens along u (α 0.1 at column 0 to 0.45 at column 7) and the
    // tables average over uv: where the lobe is narrow the samples beat
    // cosine sampling by far, at the broadest they do not (measured 0.18,
    // 0.14, 0.004, 0.55 and 1.29 of its variance; bounds about twice that;
    // 0.15, 0.09, 0.003, 0.80 and 2.27 before the texel's own diffuse
    // share). The views asked are not captured ones (but for the zenith),
    // and with only seven views each table serves a wide region.
    let m = Material::from_data(material_with_model()).unwrap();
    let lum = |c: [f32; 3]| (c[0] + c[1] + c[2]) as f64 / 3.0;
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let oblique = unit_f32([0.5, 0.2, 0.8]);
    for (uv, wo, most) in [
        ([0.1, 0.7], [0.0, 0.0, 1.0], 0.3),
        ([0.05, 0.3], oblique, 0.3),
        ([0.05, 0.3], unit_f32([-0.9, 0.3, 0.3]), 0.05),
        ([0.5, 0.3], oblique, 1.1),
        ([0.9, 0.3], oblique, 2.6),
    ] {
        let truth: f64 = hemisphere_grid(64, 128, 4)
            .map(|(_, wi, dw)| lum(m.eval(uv, wi, wo)) * dw as f64)
            .sum();
        let n = 20_000;
        let (mut s1, mut s2, mut c1, mut c2) = (0.0, 0.0, 0.0, 0.0);
        for _ in 0..n {
            let x = m
                .sample(uv, wo, rng.random(), [rng.random(), rng.random()])
                .map_or(0.0, |s| lum(s.weight()));
            (s1, s2) = (s1 + x, s2 + x * x);
            let wi = importance::cosine_direction([rng.random(), rng.random()]);
            let y = if wi[2] > 0.0 {
                lum(m.eval(uv, wi, wo)) * std::f64::consts::PI / wi[2] as f64
            } else {
                0.0
            };
            (c1, c2) = (c1 + y, c2 + y * y);
        }
        let nf = n as f64;
        let (mean, var) = (s1 / nf, s2 / nf - (s1 / nf).powi(2));
        let ratio = var / (c2 / nf - (c1 / nf).powi(2));
        let err = (mean - truth) / (var / nf).sqrt();
        assert!(err.abs() < 4.0, "{uv:?} {wo:?}: {mean} against {truth} ({err:.2} σ)");
        assert!(ratio < most, "{uv:?} {wo:?}: variance {ratio:.3} × cosine sampling's");
    }
}

#[test]
fn sampling_refuses_what_is_not_a_view() {
    let m = Material::from_data(material_with_model()).unwrap();
    for wo in [[f32::NAN, 0.0, 1.0], [0.0, 0.0, 0.0], [0.3, 0.1, -0.2], [1.0, 0.0, 0.0]] {
        assert_eq!(m.sample([0.5, 0.5], wo, 0.5, [0.5, 0.5]), None, "{wo:?}");
        assert_eq!(m.pdf([0.5, 0.5], [0.0, 0.0, 1.0], wo), 0.0, "{wo:?}");
    }
    assert_eq!(m.sample([f32::NAN, 0.5], [0.0, 0.0, 1.0], 0.5, [0.5, 0.5]), None);
    assert_eq!(m.pdf([0.5, 0.5], [0.3, 0.1, -0.2], [0.0, 0.0, 1.0]), 0.0);
    assert_eq!(m.pdf([f32::INFINITY, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]), 0.0);
    // A renderer's numbers out of [0, 1) are clamped into it, never a panic.
    for x in [f32::NAN, -1.0, 1.0, 7.0, f32::INFINITY] {
        for (uc, u) in [(x, [0.5, 0.5]), (0.5, [x, 0.5]), (0.05, [0.5, x])] {
            if let Some(s) = m.sample([0.5, 0.5], [0.0, 0.0, 1.0], uc, u) {
                assert!(s.pdf > 0.0 && s.wi[2] > 0.0, "{uc} {u:?}: {s:?}");
            }
        }
    }
}

/// `d` enlarged (version 5) to a `columns` × `rows` piece of `extent_mm`
/// whose texel (c, r) is matched at the sample's fixed-point uv
/// ((7919 (3c + r)) mod 2¹⁶, (104 729 (c + 2r)) mod 2¹⁶).
fn enlarged(mut d: MaterialData, columns: u32, rows: u32, extent_mm: [f64; 2]) -> MaterialData {
    d.meta.version = format::VERSION_ENLARGED;
    d.meta.extent_mm = extent_mm;
    d.meta.enlargement = Some(format::Enlargement {
        columns,
        rows,
        signature: "colour".into(),
        directions: vec![[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]],
        direct_sha256: "3".repeat(64),
    });
    d.enlargement = (0..rows * columns)
        .map(|i| {
            let (c, r) = (i % columns, i / columns);
            [(7919 * (3 * c + r) % 65536) as u16, (104_729 * (c + 2 * r) % 65536) as u16]
        })
        .collect();
    d
}

#[test]
fn an_enlarged_material_shades_each_texel_of_the_piece_as_its_match() {
    let mut rng = ChaCha8Rng::seed_from_u64(51);
    for (base, name) in [
        (material(Interpolation::Default), "default"),
        (material_with_model(), "texel model"),
        (with_detail(material(Interpolation::Default)), "detail layer"),
        (with_light_detail(material_with_model()), "light components"),
        (material(Interpolation::Patent { columns: 24, rows: 6, points: 10 }), "patent"),
    ] {
        // 21 × 14 texels over 2.5 × 2 sample widths: a map texel is 0.119
        // and 0.143 of the sample's side along u and v.
        let extent = [2.5 * 25.4, 2.0 * 25.4];
        let (cols, rows) = (21u32, 14u32);
        let big = enlarged(base.clone(), cols, rows, extent);
        let map = big.enlargement.clone();
        let plain = Material::from_bytes(&base.to_bytes().unwrap()).unwrap();
        let m = Material::from_bytes(&big.to_bytes().unwrap()).unwrap();
        assert_eq!(m.metadata().extent_mm, extent);
        let scale = [extent[0] / cols as f64 / 25.4, extent[1] / rows as f64 / 25.4];
        for _ in 0..300 {
            let uv = [rng.random_range(-1.0..2.0f32), rng.random_range(-1.0..2.0f32)];
            let (wi, wo) = (random_dir(&mut rng, 60.0), random_dir(&mut rng, 60.0));
            // Independently, in f64: the map texel, the offset from its
            // centre, the match moved by it.
            let wrap = |u: f32| u as f64 - (u as f64).floor();
            let (x, y) = (wrap(uv[0]) * cols as f64, wrap(uv[1]) * rows as f64);
            let (c, r) = (x.floor() as usize, y.floor() as usize);
            let [ms, mt] = map[r * cols as usize + c];
            let want_uv = [
                ((ms as f64 + 0.5) / 65536.0 + (x - c as f64 - 0.5) * scale[0])
                    .clamp(0.0, 0.999_999),
                ((mt as f64 + 0.5) / 65536.0 + (y - r as f64 - 0.5) * scale[1])
                    .clamp(0.0, 0.999_999),
            ];
            let got_uv = m.scanned_uv(uv);
            for k in 0..2 {
                assert!((got_uv[k] as f64 - want_uv[k]).abs() < 1e-5, "{name}: {uv:?}");
            }
            let (a, b) = (m.eval(uv, wi, wo), plain.eval(got_uv, wi, wo));
            assert_eq!(a, b, "{name}: {uv:?}");
        }
        // At a map texel's centre: its match.
        let at = m.scanned_uv([(4.0 + 0.5) / cols as f32, (9.0 + 0.5) / rows as f32]);
        let [ms, mt] = map[9 * cols as usize + 4];
        assert!((at[0] - (ms as f32 + 0.5) / 65536.0).abs() < 1e-6, "{name}");
        assert!((at[1] - (mt as f32 + 0.5) / 65536.0).abs() < 1e-6, "{name}");
        assert!(batch_as_eval(&m, &random_queries(&mut rng, 500)) > 0, "{name}");
        // A uv that is not finite is black, as it is without a map.
        assert_eq!(m.eval([f32::NAN, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]), [0.0; 3]);
        // Sampling goes through the map too: its draws are `eval`'s.
        m.prepare_importance();
        for _ in 0..50 {
            let uv = [rng.random_range(0.0..1.0f32), rng.random_range(0.0..1.0f32)];
            let wo = random_dir(&mut rng, 60.0);
            let u = [rng.random_range(0.0..1.0f32), rng.random_range(0.0..1.0f32)];
            if let Some(d) = m.sample(uv, wo, rng.random_range(0.0..1.0f32), u) {
                assert_eq!(d.f_cos, m.eval(uv, d.wi, wo), "{name}");
                assert_eq!(d.pdf, m.pdf(uv, d.wi, wo), "{name}");
            }
        }
    }
}

#[test]
fn bad_enlargements_are_refused() {
    let e = |d: MaterialData| match d.to_bytes() {
        Ok(_) => "accepted".to_string(),
        Err(e) => e.to_string(),
    };
    let good = || enlarged(material(Interpolation::Default), 5, 3, [40.0, 24.0]);
    assert_eq!(e(good()), "accepted");
    // Every 16-bit value is a place on the sample.
    let mut d = good();
    d.enlargement[7] = [0, u16::MAX];
    assert_eq!(e(d), "accepted");
    let mut d = good();
    d.enlargement.pop();
    assert!(e(d).contains("enlargement: 14 texels for 5 × 3"));
    let mut d = good();
    d.meta.version = format::VERSION_LIGHT_DETAIL;
    assert!(e(d).contains("version 4 with an enlargement"));
    let mut d = material(Interpolation::Default);
    d.meta.version = format::VERSION_ENLARGED;
    assert!(e(d).contains("version 5 without an enlargement"));
    for (cols, rows) in [(0, 3), (5, 0), (16385, 1)] {
        let mut d = good();
        let m = d.meta.enlargement.as_mut().unwrap();
        (m.columns, m.rows) = (cols, rows);
        d.enlargement = vec![[0, 0]; (cols * rows) as usize];
        let msg = e(d);
        assert!(msg.contains("columns and rows must be in 1…16384"), "{msg}");
    }
    for name in ["hue", "Colour", ""] {
        let mut d = good();
        d.meta.enlargement.as_mut().unwrap().signature = name.into();
        assert!(e(d).contains(&format!("enlargement signature {name:?}")), "{name}");
    }
    // Both of the patent's signatures read alike.
    let mut d = good();
    d.meta.enlargement.as_mut().unwrap().signature = "height".into();
    let m = Material::from_bytes(&d.to_bytes().unwrap()).unwrap();
    assert_eq!(m.metadata().enlargement.as_ref().unwrap().signature, "height");
    for dirs in [vec![], vec![[0.0, 0.0, 2.0]], vec![[0.6, 0.0, -0.8]]] {
        let mut d = good();
        d.meta.enlargement.as_mut().unwrap().directions = dirs;
        assert!(e(d).contains("enlargement directions"));
    }
    // A map the metadata does not announce is an unexpected tensor; one it
    // announces but the file lacks is missing.
    let bytes = good().to_bytes().unwrap();
    let stripped = with_metadata(&bytes, |json| {
        let start = json.find(",\"enlargement\"").unwrap();
        let sha = start + json[start..].find("direct_sha256").unwrap();
        let end = sha + json[sha..].find("\"}").unwrap() + 2;
        format!("{}{}", &json[..start], &json[end..]).replace("\"version\":5", "\"version\":1")
    });
    let msg = Material::from_bytes(&stripped).unwrap_err().to_string();
    assert!(msg.contains("unexpected tensor `enlargement`"), "{msg}");
    // Version 5 says by its keys what it holds: a detail layer's light
    // components still need the layer.
    let one = with_metadata(&bytes, |json| {
        json.replace("\"version\":5", "\"version\":5,\"detail_components\":1")
    });
    let msg = Material::from_bytes(&one).unwrap_err().to_string();
    assert!(msg.contains("1 light components without a detail layer"), "{msg}");
    damage_never_panics(&bytes, 17);
}
