//! The material file from region images (Fig. 6 steps 4–5, Fig. 11A's
//! tables): palettes, the direction tables of the chosen interpolation,
//! and the metadata (docs/material-format.md). The file's reader and the
//! shading it describes are `scanner-shading`.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use scanner_shading::format::{CellTable, DirectionTables, MAX_CELL_PAIRS, Mirror, Provenance};
use scanner_shading::{Interpolation, MaterialData, Metadata};
use spade::{DelaunayTriangulation, Point2, Triangulation};

use super::calibrate::BuildProgress;
use super::error::BuildError;
use super::palette::{group_lights, group_lights_into, palettise};
use super::regions::RegionSet;
use super::texel_fit::{self, unit32};
use scanner_shading::texel::TexelParams;

/// How to build a material.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaterialOptions {
    /// Colours per palette, 1…256.
    pub colours: usize,
    /// Lights sharing an index image, 1…4: the fewest; more share where
    /// the file would exceed [`MaterialOptions::max_bytes`].
    pub lights_per_index: usize,
    /// Interpolation and its tables.
    pub interpolation: Interpolation,
    /// Seed of the k-means and the patent table's random points.
    pub seed: u64,
    /// Whether a default-interpolation material carries a fitted texel
    /// model (the patent's never does).
    pub texel_model: TexelModelChoice,
    /// Largest file wanted, bytes (`None`: no limit). Where the file would
    /// be larger, more lights share an index image (up to 4), the fewest
    /// that need to.
    pub max_bytes: Option<usize>,
}

/// [`MaterialOptions::max_bytes`] by default: the 16 MB a 40 × 40 material
/// at S = 128 with 256 colours may take.
pub const MAX_BYTES: usize = 16_000_000;

/// When the builder fits and stores a texel model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TexelModelChoice {
    /// When it predicts held-out lights better (leave-one-light-out).
    #[default]
    Auto,
    /// Always.
    On,
    /// Never.
    Off,
}

impl std::str::FromStr for TexelModelChoice {
    type Err = String;

    /// `auto`, `on` or `off`.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(TexelModelChoice::Auto),
            "on" => Ok(TexelModelChoice::On),
            "off" => Ok(TexelModelChoice::Off),
            other => Err(format!("texel model {other:?}: auto, on or off")),
        }
    }
}

impl Default for MaterialOptions {
    fn default() -> Self {
        MaterialOptions {
            colours: 256,
            lights_per_index: 1,
            interpolation: Interpolation::Default,
            seed: 1,
            texel_model: TexelModelChoice::Auto,
            max_bytes: Some(MAX_BYTES),
        }
    }
}

impl MaterialOptions {
    /// Every option in range: 1…256 colours, 1…4 lights per index image,
    /// the patent table's size ([`Interpolation::check`]).
    pub fn check(&self) -> Result<(), String> {
        if !(1..=256).contains(&self.colours) {
            return Err(format!("colours must be in 1…256, got {}", self.colours));
        }
        if !(1..=4).contains(&self.lights_per_index) {
            return Err(format!(
                "lights per index image must be in 1…4, got {}",
                self.lights_per_index
            ));
        }
        self.interpolation.check()
    }
}

/// The patent table of the patent's example: 1025 × 256 cells of 0.35°,
/// 1000 points per cell.
pub const PATENT_DEFAULT: Interpolation =
    Interpolation::Patent { columns: 1025, rows: 256, points: 1000 };

/// Delaunay triangles of unit directions (z > 0), by index: triangulated in
/// the gnomonic projection (x/z, y/z), where great circles are straight
/// lines, so the planar triangles are exactly the spherical triangles the
/// barycentric weights of `scanner-shading` assume.
pub fn triangulate(dirs: &[[f64; 3]], what: &str) -> Result<Vec<[u16; 3]>, BuildError> {
    let bad = |s: String| BuildError::Input(format!("{what}: {s}"));
    let mut t = DelaunayTriangulation::<Point2<f64>>::new();
    let mut by_vertex = Vec::new();
    for (i, d) in dirs.iter().enumerate() {
        if d[2].is_nan() || d[2] <= 1e-3 {
            return Err(bad(format!("direction {i} {d:?} is not above the sample")));
        }
        let h = t
            .insert(Point2::new(d[0] / d[2], d[1] / d[2]))
            .map_err(|e| bad(format!("direction {i}: {e:?}")))?;
        if h.index() != by_vertex.len() {
            return Err(bad(format!(
                "direction {i} coincides with direction {}",
                by_vertex[h.index()]
            )));
        }
        by_vertex.push(i);
    }
    let tris: Vec<[u16; 3]> =
        t.inner_faces().map(|f| f.vertices().map(|v| by_vertex[v.fix().index()] as u16)).collect();
    if dirs.len() >= 3 && tris.is_empty() {
        return Err(bad("the directions lie on one great circle".into()));
    }
    Ok(tris)
}

/// Lines through a patent cell's centre tried for its circle.
const PATENT_LINES: usize = 16;

/// The patent's table over `dirs` (Fig. 11A steps 1–3): cell (row, column)
/// centred on θ = (row + ½)·90°/rows, φ = (column + ½)·360°/columns; its
/// circle is the smallest (geodesic) disc around the centre in which each
/// of [`PATENT_LINES`] lines through the centre crosses into a second
/// Voronoi zone; `points` uniform random points in the disc are counted by
/// nearest direction.
pub fn patent_table(
    dirs: &[[f64; 3]],
    columns: u32,
    rows: u32,
    points: u32,
    seed: u64,
) -> CellTable {
    let (cols, rws) = (columns as usize, rows as usize);
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let per_cell: Vec<Vec<(u16, u16)>> = (0..rws)
        .into_par_iter()
        .flat_map_iter(|r| {
            let theta = (r as f64 + 0.5) / rws as f64 * std::f64::consts::FRAC_PI_2;
            (0..cols).map(move |c| (r, c, theta))
        })
        .map(|(r, c, theta)| {
            let phi = (c as f64 + 0.5) / cols as f64 * std::f64::consts::TAU;
            let (st, ct, sp, cp) = (theta.sin(), theta.cos(), phi.sin(), phi.cos());
            let centre = [st * cp, st * sp, ct];
            // Tangent basis: along θ and along φ.
            let e1 = [ct * cp, ct * sp, -st];
            let e2 = [-sp, cp, 0.0];
            let nearest = |p: [f64; 3], among: &mut dyn Iterator<Item = usize>| {
                among.max_by(|&a, &b| dot(p, dirs[a]).total_cmp(&dot(p, dirs[b]))).unwrap_or(0)
            };
            let m0 = nearest(centre, &mut (0..dirs.len()));
            // Exit distance along the great circle from the centre towards u.
            let exit = |u: [f64; 3]| {
                let mut t = std::f64::consts::FRAC_PI_2;
                for (j, mj) in dirs.iter().enumerate() {
                    if j == m0 {
                        continue;
                    }
                    let diff = [mj[0] - dirs[m0][0], mj[1] - dirs[m0][1], mj[2] - dirs[m0][2]];
                    let (a, b) = (dot(centre, diff), dot(u, diff));
                    if b > 0.0 {
                        t = t.min((-a).max(0.0).atan2(b));
                    }
                }
                t
            };
            let mut radius: f64 = 0.0;
            for k in 0..PATENT_LINES {
                let a = k as f64 * std::f64::consts::PI / PATENT_LINES as f64;
                let u = std::array::from_fn(|i| a.cos() * e1[i] + a.sin() * e2[i]);
                let v = u.map(|x: f64| -x);
                radius = radius.max(exit(u).min(exit(v)));
            }
            let radius = radius.max(1e-6);
            // Only directions within angle(centre, m0) + 2r can be nearest in the disc.
            let reach = dot(centre, dirs[m0]).clamp(-1.0, 1.0).acos() + 2.0 * radius + 1e-9;
            let cands: Vec<usize> = (0..dirs.len())
                .filter(|&j| dot(centre, dirs[j]).clamp(-1.0, 1.0).acos() <= reach)
                .collect();
            let mut rng = ChaCha8Rng::seed_from_u64(
                seed ^ ((r * cols + c) as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
            );
            let mut counts = vec![0u16; dirs.len()];
            for _ in 0..points {
                let rho = radius * rng.random::<f64>().sqrt();
                let psi = rng.random::<f64>() * std::f64::consts::TAU;
                let (sr, cr) = rho.sin_cos();
                let p = std::array::from_fn(|i| {
                    cr * centre[i] + sr * (psi.cos() * e1[i] + psi.sin() * e2[i])
                });
                counts[nearest(p, &mut cands.iter().copied())] += 1;
            }
            let mut pairs: Vec<(u16, u16)> = counts
                .iter()
                .enumerate()
                .filter(|&(_, &n)| n > 0)
                .map(|(j, &n)| (j as u16, n))
                .collect();
            // The reader's bound; never reached with ≤ 64 zones in a disc.
            pairs.sort_by_key(|p| std::cmp::Reverse(p.1));
            pairs.truncate(MAX_CELL_PAIRS);
            pairs.sort_unstable();
            pairs
        })
        .collect();
    let mut t = CellTable { offsets: vec![0], ..Default::default() };
    for cell in per_cell {
        for (m, n) in cell {
            t.mirrors.push(m);
            t.counts.push(n);
        }
        t.offsets.push(t.mirrors.len() as u32);
    }
    t
}

/// A material's answers to queries of a query file (f64, normalised), in
/// parallel chunks.
pub fn shade(
    material: &scanner_shading::Material,
    queries: &[scanner_formats::queries::Query],
) -> Vec<[f32; 3]> {
    let f = |d: [f64; 3]| d.map(|x| x as f32);
    let q32: Vec<scanner_shading::ShadeQuery> = queries
        .iter()
        .map(|q| scanner_shading::ShadeQuery {
            uv: q.uv.map(|x| x as f32),
            wi: f(q.wi),
            wo: f(q.wo),
        })
        .collect();
    let mut answers = vec![[0f32; 3]; q32.len()];
    answers
        .par_chunks_mut(4096)
        .zip(q32.par_chunks(4096))
        .for_each(|(out, q)| material.eval_batch(q, out));
    answers
}

/// The half-vector shifts the builder chooses from.
pub const SHIFTS: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// Leave-one-light-out prediction errors of the default interpolation:
/// every light's images predicted from the other lights' (the shading's
/// own weights, `scanner_shading::default_pairs`) at 8 × 8 texels, the
/// mean squared error against the captured values, for each of
/// [`SHIFTS`] — `[shift][0]` without a texel model, `[shift][1]` with one
/// (fitted without the held light, residuals interpolated) when
/// `with_model`, at β = 0 only: the builder writes β = 0 with a model, so
/// the model is judged at the β it will be shaded with (infinite at the
/// other shifts). The model is fitted, subtracted and added back at each
/// texel's own directions ([`texel_fit::texel_views`]), so the prediction is
/// of the value the texel was captured with.
pub fn shift_errors(
    regions: &RegionSet,
    view_tris: &[[u16; 3]],
    with_model: bool,
) -> Result<Vec<[f64; 2]>, BuildError> {
    use scanner_shading::locate::TriangleLocator;
    use scanner_shading::texel::reflected;
    let internal = |e: scanner_shading::MaterialError| BuildError::Input(e.to_string());
    let (nl, nv, s) = (regions.lights.len(), regions.views.len(), regions.size);
    let vd: Vec<[f32; 3]> = regions.view_dirs.iter().map(|&d| unit32(d)).collect();
    let ld: Vec<[f32; 3]> = regions.light_dirs.iter().map(|&d| unit32(d)).collect();
    let views = TriangleLocator::new(&vd, view_tris, "view directions").map_err(internal)?;
    let texels: Vec<usize> = (0..64)
        .map(|i| {
            let (x, y) = ((2 * (i % 8) + 1) * s / 16, (2 * (i / 8) + 1) * s / 16);
            y * s + x
        })
        .collect();
    // Each scored texel's own view directions.
    let texel_views: Vec<_> = texels.iter().map(|&t| texel_fit::texel_views(regions, t)).collect();
    let per_light: Vec<Vec<[f64; 2]>> = (0..nl)
        .into_par_iter()
        .map(|held| {
            let others: Vec<usize> = (0..nl).filter(|&l| l != held).collect();
            let od: Vec<[f64; 3]> = others.iter().map(|&l| regions.light_dirs[l]).collect();
            let od32: Vec<[f32; 3]> = others.iter().map(|&l| ld[l]).collect();
            let Ok(lights) = triangulate(&od, "light directions").and_then(|t| {
                TriangleLocator::new(&od32, &t, "light directions").map_err(internal)
            }) else {
                return vec![[0.0; 2]; SHIFTS.len()];
            };
            // The model of each scored texel, fitted without the held light.
            let models: Vec<TexelParams> = if with_model {
                texels
                    .iter()
                    .zip(&texel_views)
                    .map(|(&t, views)| {
                        let keep: Vec<usize> = (0..nl * nv)
                            .filter(|&i| i / nv != held && !regions.is_unlit(i / nv, t))
                            .collect();
                        let d: Vec<_> = keep.iter().map(|&i| (ld[i / nv], views[i % nv])).collect();
                        let y: Vec<[f32; 3]> = keep.iter().map(|&i| regions.images[i][t]).collect();
                        texel_fit::fit_texel(&texel_fit::Observations { dirs: &d, values: &y }).0
                    })
                    .collect()
            } else {
                Vec::new()
            };
            let wi = ld[held];
            SHIFTS
                .iter()
                .map(|&shift| {
                    // The model only at β = 0, the β it is written with.
                    let models: &[TexelParams] = if shift == 0.0 { &models } else { &[] };
                    let mut err = [0.0; 2];
                    for (v, &wo) in vd.iter().enumerate() {
                        let mut pred = vec![[[0f64; 3]; 2]; texels.len()];
                        scanner_shading::default_pairs(
                            &lights,
                            &od32,
                            &views,
                            shift as f32,
                            wi,
                            wo,
                            |vi, lj, w| {
                                let l = others[lj as usize];
                                let k = w as f64 * wi[2] as f64 / ld[l][2] as f64;
                                let img = regions.image(l, vi as usize);
                                for (i, (p, &t)) in pred.iter_mut().zip(&texels).enumerate() {
                                    let m = models.get(i).map_or([0.0; 3], |m| {
                                        reflected(m, ld[l], texel_views[i][vi as usize])
                                    });
                                    for c in 0..3 {
                                        p[0][c] += k * img[t][c] as f64;
                                        p[1][c] += k * (img[t][c] - m[c]) as f64;
                                    }
                                }
                            },
                        );
                        let img = regions.image(held, v);
                        for (i, (p, &t)) in pred.iter().zip(&texels).enumerate() {
                            if regions.is_unlit(held, t) {
                                continue;
                            }
                            let m = models
                                .get(i)
                                .map_or([0.0; 3], |m| reflected(m, wi, texel_views[i][v]));
                            for c in 0..3 {
                                let y = img[t][c] as f64;
                                err[0] += (p[0][c] - y).powi(2);
                                err[1] += ((p[1][c] + m[c] as f64).max(0.0) - y).powi(2);
                            }
                        }
                    }
                    if models.is_empty() {
                        err[1] = f64::INFINITY;
                    }
                    err.map(|e| e / (nv * texels.len() * 3) as f64)
                })
                .collect()
        })
        .collect();
    Ok((0..SHIFTS.len())
        .map(|k| {
            std::array::from_fn(|m| per_light.iter().map(|e| e[k][m]).sum::<f64>() / nl as f64)
        })
        .collect())
}

/// Build the material of `regions`.
pub fn build_material(
    regions: &RegionSet,
    name: &str,
    sample_size_mm: f64,
    provenance: Provenance,
    opts: &MaterialOptions,
    progress: &dyn BuildProgress,
) -> Result<MaterialData, BuildError> {
    opts.check().map_err(BuildError::Input)?;
    let (nl, nv, s) = (regions.lights.len(), regions.views.len(), regions.size);
    let g = opts.lights_per_index.min(nl);
    let mut light_groups = group_lights(&regions.light_dirs, g);
    let mut groups = light_groups.iter().map(|&x| x as usize + 1).max().unwrap_or(0);
    if let Some(max) = opts.max_bytes {
        // Everything but the index images (a texel model counted whether or
        // not it is chosen below; 64 KB for the tables and the header),
        // then as many index images as fit, if fewer than g gives.
        let k = opts.colours;
        let fixed = nl * nv * k * 6
            + s * s * scanner_shading::texel::STORED * 2
            + regions
                .detail
                .as_ref()
                .map_or(0, |d| (1 + d.bases.len()) * d.shared.len() * 6 + d.bases.len() * nl * 4)
            + 65_536;
        let fit = max.saturating_sub(fixed) / (nv * s * s).max(1);
        if fit < groups {
            groups = fit.max(nl.div_ceil(4)).max(1);
            light_groups = group_lights_into(&regions.light_dirs, groups);
        }
    }
    let g = (0..groups)
        .map(|grp| light_groups.iter().filter(|&&x| x as usize == grp).count())
        .max()
        .unwrap_or(1);
    let members: Vec<Vec<usize>> = (0..groups)
        .map(|grp| (0..nl).filter(|&l| light_groups[l] as usize == grp).collect())
        .collect();
    let mut half_vector_shift = 0.0;
    let mut texel_model = false;
    let tables = match opts.interpolation {
        Interpolation::Default => {
            let views = triangulate(&regions.view_dirs, "view directions")?;
            let lights = triangulate(&regions.light_dirs, "light directions")?;
            texel_model = opts.texel_model == TexelModelChoice::On;
            if nl >= 4 {
                progress.stage("interpolation choice", 1);
                let with_model = opts.texel_model != TexelModelChoice::Off;
                let errs = shift_errors(regions, &views, with_model)?;
                let allowed: &[usize] = match opts.texel_model {
                    TexelModelChoice::Auto => &[0, 1],
                    TexelModelChoice::On => &[1],
                    TexelModelChoice::Off => &[0],
                };
                let best = (0..SHIFTS.len())
                    .flat_map(|k| allowed.iter().map(move |&m| (k, m)))
                    .min_by(|a, b| errs[a.0][a.1].total_cmp(&errs[b.0][b.1]))
                    .unwrap_or((0, 0));
                texel_model = best.1 == 1;
                // With a texel model, the model puts each highlight where the
                // query's half vector does and only its residuals are
                // interpolated: at novel pairs every β scores within 0.17 dB
                // and β = 0 best or within 0.01 dB on seven samples, though
                // a held-out light, a whole light spacing from the others,
                // prefers ½ or ¾ (docs/benchmarks.md, "The half-vector
                // shift's choice"). β = 0 lets a query's lights share one
                // view lookup, so the model is only scored at β = 0.
                half_vector_shift = SHIFTS[best.0];
                progress.step();
            }
            DirectionTables::Triangles { views, lights }
        }
        Interpolation::Patent { columns, rows, points } => {
            progress.stage("patent tables", 2);
            let views = patent_table(&regions.view_dirs, columns, rows, points, opts.seed);
            progress.step();
            let lights = patent_table(&regions.light_dirs, columns, rows, points, opts.seed ^ 1);
            progress.step();
            DirectionTables::Patent { views, lights }
        }
    };
    let texels = if texel_model {
        progress.stage("texel model", 2 * s);
        texel_fit::fit_texels(regions, &|| progress.step())
    } else {
        Vec::new()
    };
    // The texels a beam left unlit, filled again from the lights that lit
    // them with the model's own values added (extraction filled them
    // without a model).
    let refilled;
    let regions = if texels.is_empty() || regions.unlit.iter().all(|u| u.is_empty()) {
        regions
    } else {
        let mut again = regions.clone();
        let ld: Vec<[f32; 3]> = regions.light_dirs.iter().map(|&d| unit32(d)).collect();
        let model = |l: usize, vi: usize, t: usize| {
            let wo = unit32(regions.view_dir_at(vi, regions.texel_uv(t)));
            scanner_shading::texel::reflected(&texels[t], ld[l], wo)
        };
        again.fill_unlit(Some(&model));
        refilled = again;
        &refilled
    };
    let k = opts.colours;
    progress.stage("palettes", nv);
    let per_view: Vec<Vec<super::palette::GroupPalettes>> = (0..nv)
        .into_par_iter()
        .map(|vi| {
            let out = members
                .par_iter()
                .enumerate()
                .map(|(grp, ls)| {
                    // With a texel model, each image as the model carries it to
                    // the pair's central directions (the shading's M(lⱼ, vᵢ)).
                    let held: Vec<_> = ls
                        .iter()
                        .map(|&l| texel_fit::held_image(regions, &texels, l, vi))
                        .collect();
                    let imgs: Vec<&[[f32; 3]]> = held.iter().map(|i| i.as_ref()).collect();
                    let seed =
                        opts.seed ^ ((vi * 256 + grp) as u64).wrapping_mul(0x2545_f491_4f6c_dd1d);
                    palettise(&imgs, k, seed)
                })
                .collect();
            progress.step();
            out
        })
        .collect();
    let mut indices = vec![0u8; nv * s * s * groups];
    let mut palettes = vec![[0f32; 3]; nl * nv * k];
    for (vi, view) in per_view.iter().enumerate() {
        for (grp, gp) in view.iter().enumerate() {
            for (t, &i) in gp.indices.iter().enumerate() {
                indices[(vi * s * s + t) * groups + grp] = i;
            }
            for (slot, &l) in members[grp].iter().enumerate() {
                let dst = &mut palettes[(l * nv + vi) * k..][..k];
                for (d, src) in dst.iter_mut().zip(&gp.palettes[slot]) {
                    *d = *src;
                }
            }
        }
    }
    let mirror = |m: &usize, d: &[f64; 3]| {
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        Mirror { mirror: *m as u32, direction: d.map(|x| x / len) }
    };
    let (detail, detail_bases, detail_coefficients, components) = detail_tensors(regions);
    let with_detail = !detail.is_empty();
    Ok(MaterialData {
        meta: Metadata {
            format: scanner_shading::format::FORMAT.into(),
            version: if components > 0 {
                scanner_shading::format::VERSION_LIGHT_DETAIL
            } else if with_detail {
                scanner_shading::format::VERSION_DETAIL
            } else if texel_model {
                scanner_shading::format::VERSION_TEXEL_MODEL
            } else {
                scanner_shading::format::VERSION
            },
            name: name.into(),
            sample_size_mm,
            extent_mm: [sample_size_mm, sample_size_mm],
            resolution: s as u32,
            colours: k as u32,
            lights_per_index: g as u32,
            interpolation: opts.interpolation,
            half_vector_shift,
            lights: regions
                .lights
                .iter()
                .zip(&regions.light_dirs)
                .map(|(m, d)| mirror(m, d))
                .collect(),
            views: regions
                .views
                .iter()
                .zip(&regions.view_dirs)
                .map(|(m, d)| mirror(m, d))
                .collect(),
            provenance: Provenance {
                face: provenance.face.or_else(|| Some(regions.face_record())),
                ..provenance
            },
            texel_model,
            detail: with_detail,
            detail_components: components as u32,
            enlargement: None,
        },
        palettes,
        indices,
        light_groups,
        tables,
        texels,
        detail,
        detail_bases,
        detail_coefficients,
        enlargement: Vec::new(),
    })
}

/// The region set's detail layer as the file stores it: the shared factors
/// (within the file's range after rounding to float16), the light
/// components (`[R][2S][2S]`, within −1…1) and their coefficients
/// (`[L][R]`, within the file's range), and R. All empty without a layer.
#[allow(clippy::type_complexity)]
fn detail_tensors(regions: &RegionSet) -> (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<f32>, usize) {
    use scanner_shading::format::{DETAIL_COEFFICIENT_RANGE, DETAIL_RANGE};
    let Some(d) = &regions.detail else {
        return (Vec::new(), Vec::new(), Vec::new(), 0);
    };
    let finite =
        |x: f32, lo: f32, hi: f32, or: f32| if x.is_finite() { x.clamp(lo, hi) } else { or };
    let shared = d
        .shared
        .iter()
        .map(|v| v.map(|x| finite(x, 1.0 / DETAIL_RANGE, DETAIL_RANGE, 1.0)))
        .collect();
    let bases = d.bases.iter().flatten().map(|v| v.map(|x| finite(x, -1.0, 1.0, 0.0))).collect();
    let range = DETAIL_COEFFICIENT_RANGE;
    let coefficients =
        d.coefficients.iter().flatten().map(|&x| finite(x, -range, range, 0.0)).collect();
    (shared, bases, coefficients, d.bases.len())
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use scanner_geometry::ScannerGeometry;
    use scanner_shading::locate::{TriangleLocator, Weights3};

    use super::{
        MaterialOptions, SHIFTS, TexelModelChoice, build_material, shift_errors, triangulate,
    };
    use crate::build::RegionSet;
    use crate::build::calibrate::Silent;
    use crate::build::superres::DetailLayer;

    /// `n` directions on three rings (10°, 25°, 40°) as both lights and
    /// views, S × S texels, `image(dirs, light, view, texel)` each pair's
    /// values.
    fn ring_regions(
        n: usize,
        s: usize,
        image: impl Fn(&[[f64; 3]], usize, usize, usize) -> [f32; 3],
    ) -> RegionSet {
        let dirs: Vec<[f64; 3]> = (0..n)
            .map(|k| {
                let (th, ph) = ((10.0 + 15.0 * (k % 3) as f64).to_radians(), 0.9 * k as f64);
                [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()]
            })
            .collect();
        RegionSet {
            size: s,
            lights: (0..n).collect(),
            views: (0..n).collect(),
            light_dirs: dirs.clone(),
            view_dirs: dirs.clone(),
            viewers_mm: dirs.iter().map(|d| d.map(|x| x * 1200.0)).collect(),
            sample_mm: 25.4,
            images: (0..n * n)
                .map(|p| (0..s * s).map(|t| image(&dirs, p / n, p % n, t)).collect())
                .collect(),
            detail: None,
            face: scanner_geometry::SampleFace::FLUSH,
            height_fit: None,
            beyond: None,
            unlit: Vec::new(),
            sides: crate::build::regions::SampleSides::Hidden,
        }
    }

    fn provenance() -> scanner_shading::format::Provenance {
        scanner_shading::format::Provenance {
            scan_manifest_sha256: String::new(),
            geometry_sha256: String::new(),
            calibration_sha256: String::new(),
            builder: "test".into(),
            face: None,
        }
    }

    /// The detail layer's light components go into the file in its layout
    /// ([R][2S][2S], [L][R]) and come back out of the shading: at a captured
    /// pair and a 2S texel centre, the material answers its region image
    /// times its own light's factor.
    #[test]
    fn the_built_file_shades_each_light_with_its_own_detail() {
        let (n, s) = (9usize, 8usize);
        let f = 2 * s;
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        // Few colours per image, so that 256-colour palettes hold them.
        let mut regions = ring_regions(n, s, |dirs, l, v, t| {
            let cos = dirs[l][2] as f32;
            [0.1 + 0.02 * (t % 5) as f32, 0.2, 0.05 * (l * n + v) as f32 + 0.01].map(|x| x * cos)
        });
        let dirs = regions.light_dirs.clone();
        regions.detail = Some(DetailLayer {
            shared: (0..f * f).map(|_| [rng.random_range(0.7..1.4); 3]).collect(),
            bases: (0..2)
                .map(|_| {
                    (0..f * f)
                        .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
                        .collect()
                })
                .collect(),
            coefficients: (0..n)
                .map(|l| vec![0.1 * l as f32 - 0.4, 0.3 - 0.05 * l as f32])
                .collect(),
        });
        let opts = MaterialOptions { texel_model: TexelModelChoice::Off, ..Default::default() };
        let data = build_material(&regions, "test", 25.4, provenance(), &opts, &Silent).unwrap();
        assert_eq!(data.meta.version, scanner_shading::format::VERSION_LIGHT_DETAIL);
        // The face the images were read on, in the provenance.
        let face = data.meta.provenance.face.clone().unwrap();
        assert_eq!(face, regions.face_record());
        assert_eq!((face.height_mm, face.measured_on.as_str()), (regions.face.height_mm, "given"));
        assert_eq!(data.meta.detail_components, 2);
        let m = scanner_shading::Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
        let f32v = |d: [f64; 3]| d.map(|x| x as f32);
        for _ in 0..300 {
            let (li, vi) = (rng.random_range(0..n), rng.random_range(0..n));
            let (x, y) = (rng.random_range(1..f - 1), rng.random_range(1..f - 1));
            let uv = [(x as f64 + 0.5) / f as f64, (y as f64 + 0.5) / f as f64];
            let got = m.eval(uv.map(|x| x as f32), f32v(dirs[li]), f32v(dirs[vi]));
            let (img, d) = (regions.sample(li, vi, uv), regions.detail_at(li, uv));
            for k in 0..3 {
                let want = (img[k] * d[k]) as f32;
                assert!(
                    (got[k] - want).abs() <= 2e-3 * want.abs() + 1e-5,
                    "pair ({li}, {vi}) at {uv:?}: {got:?} against {want}"
                );
            }
        }
    }

    /// The builder writes β = 0 with a texel model, so the leave-one-light-out
    /// test judges the model at β = 0 alone: a model is kept only if it
    /// predicts held-out lights better at β = 0 than the best β without one.
    #[test]
    fn a_texel_model_is_judged_at_the_shift_it_is_written_with() {
        use scanner_shading::texel::{TexelParams, reflected};
        let (n, s) = (9usize, 8usize);
        let unit = |d: [f64; 3]| d.map(|x| x as f32);
        // A glossy dielectric whose normal and roughness vary over the texels.
        let texel = |t: usize| TexelParams {
            diffuse: [0.2, 0.15, 0.1],
            specular: [0.04; 3],
            alpha: 0.2 + 0.02 * (t % 7) as f32,
            normal: {
                let (x, y) = (0.05 * ((t % 5) as f32 - 2.0), 0.04 * ((t / 8 % 3) as f32 - 1.0));
                [x, y, (1.0 - x * x - y * y).sqrt()]
            },
        };
        let glossy =
            ring_regions(n, s, |dirs, l, v, t| reflected(&texel(t), unit(dirs[l]), unit(dirs[v])));
        let tris = triangulate(&glossy.view_dirs, "view directions").unwrap();
        let with = shift_errors(&glossy, &tris, true).unwrap();
        let without = shift_errors(&glossy, &tris, false).unwrap();
        assert_eq!(with.len(), SHIFTS.len());
        assert!(with[0][1].is_finite(), "{with:?}");
        for (k, (w, o)) in with.iter().zip(&without).enumerate() {
            assert_eq!(w[0], o[0], "shift {k}: the model-free errors depend on the model");
            assert!(o[1].is_infinite());
            assert!(k == 0 || w[1].is_infinite(), "shift {k}: the model judged at β ≠ 0");
        }
        let best_without = without.iter().map(|e| e[0]).fold(f64::INFINITY, f64::min);
        assert!(with[0][1] < best_without, "{with:?}");
        let opts = MaterialOptions { texel_model: TexelModelChoice::Auto, ..Default::default() };
        let data = build_material(&glossy, "glossy", 25.4, provenance(), &opts, &Silent).unwrap();
        assert!(data.meta.texel_model);
        assert_eq!(data.meta.half_vector_shift, 0.0);
    }

    /// The locator's fast path and coarse grid against its exhaustive
    /// search, on real triangulations: the default scanner's view and
    /// light directions and scattered random sets, over the whole
    /// hemisphere (beyond the outer ring too, down to the horizon).
    #[test]
    fn the_locator_agrees_with_its_exhaustive_search_on_scanner_triangulations() {
        let g = ScannerGeometry::default_scanner();
        let n = g.mirrors.len();
        let mut sets: Vec<Vec<[f64; 3]>> = vec![
            (0..n).map(|v| g.mirror_direction(v).unwrap().to_array()).collect(),
            (0..n).filter_map(|l| g.light_direction(l).ok().map(|d| d.to_array())).collect(),
        ];
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for count in [3, 5, 12, 40] {
            sets.push(
                (0..count)
                    .map(|_| {
                        let t = rng.random::<f64>() * 75f64.to_radians();
                        let p = rng.random::<f64>() * std::f64::consts::TAU;
                        [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
                    })
                    .collect(),
            );
        }
        for dirs in &sets {
            let tris = triangulate(dirs, "test").unwrap();
            let d32: Vec<[f32; 3]> = dirs.iter().map(|d| d.map(|x| x as f32)).collect();
            let loc = TriangleLocator::new(&d32, &tris, "test").unwrap();
            let dense = |w: &Weights3| {
                let mut v = vec![0f32; dirs.len()];
                for &(i, x) in w {
                    v[i as usize] += x;
                }
                v
            };
            for _ in 0..200_000 {
                let z = rng.random::<f32>().max(1e-4);
                let p = rng.random::<f32>() * std::f32::consts::TAU;
                let r = (1.0 - z * z).sqrt();
                let d = [r * p.cos(), r * p.sin(), z];
                let (mut a, mut b) = ([(0, 0.0); 3], [(0, 0.0); 3]);
                loc.weights(d, &mut a);
                loc.weights_exhaustive(d, &mut b);
                let (da, db) = (dense(&a), dense(&b));
                assert!(
                    da.iter().zip(&db).all(|(x, y)| (x - y).abs() < 1e-5),
                    "{} directions, {d:?}: {a:?} against {b:?}",
                    dirs.len()
                );
            }
        }
    }
}
