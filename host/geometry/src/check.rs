//! A scanner design checked before anything is built or scanned: what
//! each mirror sees and lights, and what would make a scan of it fail or
//! mislead (`scanner geometry`, docs/scanner-geometry.md "Checking a
//! design"): views off the sensor or crowding each other, mirrors too
//! small or in each other's way, light that leaves part of the sample dark
//! or reaches it from two mirrors at once.
//!
//! Every figure comes from the geometry's own kinematics and projections
//! ([`ScannerGeometry::mirror_axes`], [`ScannerGeometry::beam`],
//! [`ScannerGeometry::first_mirror`], [`crate::CameraSpec::project`]): the
//! nominal design, with no manufacturing error. Calibration finds a view
//! up to ≈ 60 px (of a 4096² sensor at f = 5 600 px) from where the design
//! puts it, so a design needs that much room around each view.

use crate::{AxisValues, DVec3, ScannerGeometry};

/// Room a view needs on every side, px at f = 5 600 px (scaled with the
/// focal length): the calibration's search margin, within which a built
/// scanner's view may lie from its nominal place.
pub const VIEW_MARGIN_PX: f64 = 60.0;

/// What one mirror does in the design.
#[derive(Debug, Clone, PartialEq)]
pub struct MirrorCheck {
    /// The mirror.
    pub mirror: usize,
    /// Unit direction from the sample's centre to the mirror's centre,
    /// sample-local (the view direction).
    pub view: DVec3,
    /// The light direction (sample-local), if the beam can be aimed at it.
    pub light: Option<DVec3>,
    /// The inverse kinematics' axis positions, if any.
    pub axes: Option<AxisValues>,
    /// The sample's corners on the sensor through this mirror, px, if in
    /// front of the camera.
    pub corners_px: Option<[[f64; 2]; 4]>,
    /// The view's resolution: the shortest distance between opposite
    /// sides of the sample's image, px, over the sample's side, mm.
    pub px_per_mm: Option<f64>,
    /// The least relative irradiance this mirror's light puts on the
    /// sample, over its corners, edge midpoints and centre (1: the beam's
    /// full core everywhere; 0: some of the sample is unlit).
    pub lit: Option<f64>,
}

/// A fault of a design.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DesignProblem {
    /// The beam cannot be aimed at the mirror, or it meets another first.
    #[error("mirror {mirror}: the light cannot reach it: {reason}")]
    Unlit {
        /// The mirror.
        mirror: usize,
        /// Why.
        reason: String,
    },
    /// Part of the sample gets less than the beam's full core from this
    /// mirror (a problem where it gets no light at all, else a warning).
    #[error(
        "mirror {mirror}: lights part of the sample at {:.0} % of the beam's core \
         (the mirror is too small, or another mirror shades it, or the beam is too narrow)",
        100.0 * lit
    )]
    PartlyLit {
        /// The mirror.
        mirror: usize,
        /// The least relative irradiance on the sample.
        lit: f64,
    },
    /// The beam aimed at one mirror also lights another whose light
    /// reaches the sample: the sample lit from two directions at once.
    #[error(
        "mirror {mirror}: its beam also lights mirror {also}, whose light reaches the sample \
         (two light directions at once: the mirrors are too close, or the beam too wide)"
    )]
    StrayLight {
        /// The mirror aimed at.
        mirror: usize,
        /// The other mirror lit.
        also: usize,
    },
    /// The inverse kinematics put an axis outside its travel.
    #[error("mirror {mirror}: {error}")]
    OutOfTravel {
        /// The mirror.
        mirror: usize,
        /// Which axis, where, and its travel.
        error: crate::StepsError,
    },
    /// The camera cannot see the whole sample in the mirror.
    #[error("mirror {mirror}: the camera sees part of the sample {reason}")]
    ViewCut {
        /// The mirror.
        mirror: usize,
        /// How: past the mirror's edge, through another mirror.
        reason: String,
    },
    /// The sample's image through the mirror, with its margin, leaves the
    /// sensor.
    #[error(
        "mirror {mirror}: its view of the sample comes within {gap_px:.0} px of the sensor's \
         edge (it needs {need_px:.0} px: a built scanner's view may lie that far from the design's)"
    )]
    OffSensor {
        /// The mirror.
        mirror: usize,
        /// The least distance to the sensor's edge (negative: outside), px.
        gap_px: f64,
        /// The margin a view needs, px.
        need_px: f64,
    },
    /// Two views lie too close on the sensor.
    #[error(
        "mirrors {a} and {b}: their views of the sample come within {gap_px:.0} px of each \
         other{} (calibration needs {need_px:.0} px to tell them apart)",
        if *gap_px <= 0.0 { ", overlapping" } else { "" }
    )]
    ViewsTooClose {
        /// One mirror.
        a: usize,
        /// The other.
        b: usize,
        /// Their least distance, px (0: they overlap).
        gap_px: f64,
        /// The margin two views need between them, px.
        need_px: f64,
    },
}

/// A design's check: every mirror's figures and every problem found.
#[derive(Debug, Clone, PartialEq)]
pub struct DesignCheck {
    /// Per mirror, in order.
    pub mirrors: Vec<MirrorCheck>,
    /// The two views closest to each other on the sensor and their
    /// distance, px (None with fewer than two views on the sensor).
    pub closest_views: Option<(usize, usize, f64)>,
    /// What would make a scan fail or mislead; empty for a sound design.
    pub problems: Vec<DesignProblem>,
    /// What a scan survives at some cost: part of the sample in the beam's
    /// soft edge (the white target's scan calibrates the weaker light
    /// out, at a lower signal there).
    pub warnings: Vec<DesignProblem>,
}

/// The axes of `axes` outside their travel under `configs` (the one
/// conversion, [`crate::unit_to_steps`], so that a design passes here
/// exactly when `scanner setup` can write its mirror table).
fn travel_problems(
    mirror: usize,
    axes: AxisValues,
    configs: &[protocol::AxisConfig; 3],
) -> Vec<DesignProblem> {
    protocol::Axis::ALL
        .into_iter()
        .zip(axes.to_array())
        .zip(configs)
        .filter_map(|((axis, value), c)| crate::unit_to_steps(axis, value, c).err())
        .map(|error| DesignProblem::OutOfTravel { mirror, error })
        .collect()
}

/// Points of the sample (uv) at which lighting and sight are checked: a
/// 5 × 5 grid from corner to corner (corners, edges and centre included).
fn probes() -> impl Iterator<Item = [f64; 2]> {
    (0..25).map(|k| [(k % 5) as f64 / 4.0, (k / 5) as f64 / 4.0])
}

impl ScannerGeometry {
    /// The margin a view needs around it on this sensor, px.
    pub fn view_margin_px(&self) -> f64 {
        VIEW_MARGIN_PX * self.camera.focal_px / 5600.0
    }

    /// Check the design (see the module documentation) on the default axes
    /// of spec/hardware.md ([`protocol::default_axes`]).
    pub fn check_design(&self) -> DesignCheck {
        self.check_design_on(&protocol::default_axes())
    }

    /// Check the design on a device's axes: `axes` gives their travel.
    pub fn check_design_on(&self, axes: &[protocol::AxisConfig; 3]) -> DesignCheck {
        let (mut problems, mut warnings) = (Vec::new(), Vec::new());
        let mirrors: Vec<MirrorCheck> = (0..self.mirrors.len())
            .map(|l| self.check_mirror(l, axes, &mut problems, &mut warnings))
            .collect();
        let need = self.view_margin_px();
        let mut closest: Option<(usize, usize, f64)> = None;
        for (i, a) in mirrors.iter().enumerate() {
            for b in &mirrors[i + 1..] {
                let (Some(pa), Some(pb)) = (a.corners_px, b.corners_px) else { continue };
                let gap = quad_distance(&pa, &pb);
                if closest.is_none_or(|c| gap < c.2) {
                    closest = Some((a.mirror, b.mirror, gap));
                }
                if gap < need {
                    problems.push(DesignProblem::ViewsTooClose {
                        a: a.mirror,
                        b: b.mirror,
                        gap_px: gap,
                        need_px: need,
                    });
                }
            }
        }
        DesignCheck { mirrors, closest_views: closest, problems, warnings }
    }

    fn check_mirror(
        &self,
        l: usize,
        configs: &[protocol::AxisConfig; 3],
        problems: &mut Vec<DesignProblem>,
        warnings: &mut Vec<DesignProblem>,
    ) -> MirrorCheck {
        let m = &self.mirrors[l];
        let mut out = MirrorCheck {
            mirror: l,
            view: self.mirror_direction(l).expect("a mirror of this geometry"),
            light: None,
            axes: None,
            corners_px: None,
            px_per_mm: None,
            lit: None,
        };
        // Light: aim the beam, then follow the light back from points of
        // the sample to the mirror and to the beam.
        match self.mirror_axes(l) {
            Err(e) => problems.push(DesignProblem::Unlit { mirror: l, reason: e.to_string() }),
            Ok(axes) => {
                out.axes = Some(axes);
                problems.extend(travel_problems(l, axes, configs));
                let beam = self.beam(axes);
                match self.first_mirror(beam.origin, beam.dir) {
                    Some((k, _)) if k == l => {
                        out.light = self.light_direction(l).ok();
                        let reflected = m.reflect_dir(beam.dir);
                        let lit = probes()
                            .map(|uv| {
                                let s = self.sample_point(uv);
                                match self.first_mirror(s, -reflected) {
                                    Some((k, q)) if k == l => self.source.profile(beam.distance(q)),
                                    _ => 0.0,
                                }
                            })
                            .fold(1.0, f64::min);
                        out.lit = Some(lit);
                        if let Some(k) = self.stray_light(l, &beam) {
                            problems.push(DesignProblem::StrayLight { mirror: l, also: k });
                        }
                        // Unlit somewhere: no signal there. In the soft
                        // edge: calibrated, at a cost.
                        if lit <= 0.0 {
                            problems.push(DesignProblem::PartlyLit { mirror: l, lit });
                        } else if lit < 1.0 {
                            warnings.push(DesignProblem::PartlyLit { mirror: l, lit });
                        }
                    }
                    Some((k, _)) => problems.push(DesignProblem::Unlit {
                        mirror: l,
                        reason: format!("the beam meets mirror {k} first"),
                    }),
                    None => problems.push(DesignProblem::Unlit {
                        mirror: l,
                        reason: "the beam misses it".into(),
                    }),
                }
            }
        }
        // Sight: each probe's mirror image must be seen through this mirror
        // and no other.
        let camera = DVec3::from(self.camera.position_mm);
        for uv in probes() {
            let image = m.reflect_point(self.sample_point(uv));
            let reason = match self.first_mirror(camera, (image - camera).normalize()) {
                Some((k, _)) if k == l => continue,
                Some((k, _)) => format!("through mirror {k} (it stands in the way)"),
                None => "past the mirror's edge (the mirror is too small or turned away)".into(),
            };
            problems.push(DesignProblem::ViewCut { mirror: l, reason });
            break;
        }
        out.corners_px = self.sample_image_corners(l);
        if let Some(c) = out.corners_px {
            let side = |a: usize, b: usize, d: usize, e: usize| {
                let mid = |p: [f64; 2], q: [f64; 2]| [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
                let (p, q) = (mid(c[a], c[b]), mid(c[d], c[e]));
                (p[0] - q[0]).hypot(p[1] - q[1])
            };
            // Corners in order around the sample: sides 01 ∥ 32, 12 ∥ 03.
            let across = side(0, 3, 1, 2).min(side(0, 1, 3, 2));
            out.px_per_mm = Some(across / self.sample.size_mm);
            let (w, h) = (self.camera.width as f64, self.camera.height as f64);
            let gap = c
                .iter()
                .map(|p| p[0].min(p[1]).min(w - p[0]).min(h - p[1]))
                .fold(f64::INFINITY, f64::min);
            let need = self.view_margin_px();
            if gap < need {
                problems.push(DesignProblem::OffSensor { mirror: l, gap_px: gap, need_px: need });
            }
        } else {
            problems.push(DesignProblem::ViewCut { mirror: l, reason: "behind the camera".into() });
        }
        out
    }

    /// Another mirror than `l` that `beam` (aimed at `l`) lights and whose
    /// light reaches the sample, if any: the light from two directions at
    /// once.
    fn stray_light(&self, l: usize, beam: &crate::Beam) -> Option<usize> {
        let reach = self.source.beam_radius_mm;
        (0..self.mirrors.len()).filter(|&k| k != l).find(|&k| {
            let m = &self.mirrors[k];
            // Its front towards the beam, and the beam tube can overlap it.
            let near = beam.dir.dot(DVec3::from(m.normal)) < 0.0
                && beam.distance(m.center()) < reach + m.size_mm * std::f64::consts::FRAC_1_SQRT_2;
            if !near {
                return false;
            }
            let d = m.reflect_dir(beam.dir);
            d.z > 0.0
                && probes().any(|uv| match self.first_mirror(self.sample_point(uv), -d) {
                    Some((j, q)) => {
                        j == k
                            && (q - beam.origin).dot(beam.dir) > 0.0
                            && self.source.profile(beam.distance(q)) > 0.0
                    }
                    None => false,
                })
        })
    }
}

/// The least distance between two convex quadrilaterals (corners in order
/// around each), 0 if they overlap.
fn quad_distance(a: &[[f64; 2]; 4], b: &[[f64; 2]; 4]) -> f64 {
    if a.iter().any(|p| inside(b, *p)) || b.iter().any(|p| inside(a, *p)) {
        return 0.0;
    }
    let mut best = f64::INFINITY;
    for i in 0..4 {
        for j in 0..4 {
            let d = segment_distance([a[i], a[(i + 1) % 4]], [b[j], b[(j + 1) % 4]]);
            best = best.min(d);
        }
    }
    best
}

/// Whether `p` lies inside the convex quadrilateral `q` (either winding).
fn inside(q: &[[f64; 2]; 4], p: [f64; 2]) -> bool {
    let cross = |i: usize| {
        let (a, b) = (q[i], q[(i + 1) % 4]);
        (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    };
    let s: Vec<f64> = (0..4).map(cross).collect();
    s.iter().all(|&x| x >= 0.0) || s.iter().all(|&x| x <= 0.0)
}

/// The least distance between two segments (0 if they cross).
fn segment_distance(s: [[f64; 2]; 2], t: [[f64; 2]; 2]) -> f64 {
    let orient = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    };
    let crosses = orient(s[0], s[1], t[0]) * orient(s[0], s[1], t[1]) < 0.0
        && orient(t[0], t[1], s[0]) * orient(t[0], t[1], s[1]) < 0.0;
    if crosses {
        return 0.0;
    }
    let point_segment = |p: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len2 = dx * dx + dy * dy;
        let t = if len2 > 0.0 {
            (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
    };
    point_segment(s[0], t[0], t[1])
        .min(point_segment(s[1], t[0], t[1]))
        .min(point_segment(t[0], s[0], s[1]))
        .min(point_segment(t[1], s[0], s[1]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_distance_between_quadrilaterals() {
        let sq = |x: f64, y: f64| [[x, y], [x + 1.0, y], [x + 1.0, y + 1.0], [x, y + 1.0]];
        assert_eq!(quad_distance(&sq(0.0, 0.0), &sq(0.5, 0.5)), 0.0);
        assert!((quad_distance(&sq(0.0, 0.0), &sq(3.0, 0.0)) - 2.0).abs() < 1e-12);
        assert!((quad_distance(&sq(0.0, 0.0), &sq(4.0, 5.0)) - 5.0).abs() < 1e-12);
        // One inside the other; a cross of two thin bars (no corner inside).
        let big = [[-5.0, -5.0], [5.0, -5.0], [5.0, 5.0], [-5.0, 5.0]];
        assert_eq!(quad_distance(&big, &sq(0.0, 0.0)), 0.0);
        let bar = [[-3.0, -0.1], [3.0, -0.1], [3.0, 0.1], [-3.0, 0.1]];
        let other = [[-0.1, -3.0], [0.1, -3.0], [0.1, 3.0], [-0.1, 3.0]];
        assert_eq!(quad_distance(&bar, &other), 0.0);
    }

    fn other_rings() -> ScannerGeometry {
        ScannerGeometry::generate_with_rings(&[(18.0, 5), (38.0, 8), (58.0, 11)])
    }

    #[test]
    fn the_default_scanner_and_another_are_sound() {
        for g in [ScannerGeometry::default_scanner(), other_rings()] {
            let c = g.check_design();
            assert_eq!(c.problems, [], "{:?}", c.problems);
            assert_eq!(c.warnings, []);
            assert_eq!(c.mirrors.len(), g.mirrors.len());
            for m in &c.mirrors {
                assert_eq!(m.lit, Some(1.0), "mirror {}", m.mirror);
                let light = m.light.expect("aimed");
                assert!(light.angle_between(g.light_direction(m.mirror).unwrap()) < 1e-9);
                assert!((m.view - g.mirror_direction(m.mirror).unwrap()).length() < 1e-12);
                // The outer ring's foreshortened views resolve least.
                assert!((2.0..5.0).contains(&m.px_per_mm.unwrap()), "{m:?}");
            }
            let (_, _, gap) = c.closest_views.unwrap();
            assert!(gap > 200.0, "closest views {:?}", c.closest_views);
        }
        // The default's views: 2.10 px/mm across the outermost ring's most
        // foreshortened view, 4.52 at the innermost.
        let c = ScannerGeometry::default_scanner().check_design();
        let res: Vec<f64> = c.mirrors.iter().map(|m| m.px_per_mm.unwrap()).collect();
        let (lo, hi) = res.iter().fold((f64::MAX, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
        assert!((lo - 2.105).abs() < 0.01 && (hi - 4.520).abs() < 0.01, "{lo} {hi}");
    }

    #[test]
    fn axes_outside_their_travel_are_named() {
        let g = ScannerGeometry::default_scanner();
        let out_of_travel = |c: &DesignCheck| -> Vec<(usize, protocol::Axis, f64, f64, f64)> {
            c.problems
                .iter()
                .map(|p| match p {
                    DesignProblem::OutOfTravel {
                        mirror,
                        error: crate::StepsError::OutOfRange { axis, value, min, max, per_unit, .. },
                    } => (*mirror, *axis, *value, *min as f64 / per_unit, *max as f64 / per_unit),
                    other => panic!("{other}"),
                })
                .collect()
        };
        // A track of 20 mm: the working position, 30 mm, lies beyond it.
        let mut axes = protocol::default_axes();
        axes[1].max_steps = (20.0 * axes[1].steps_per_unit) as i32;
        let c = g.check_design_on(&axes);
        let found = out_of_travel(&c);
        assert_eq!(found.len(), g.mirrors.len());
        for (l, f) in found.iter().enumerate() {
            assert_eq!((f.0, f.1), (l, protocol::Axis::Track));
            assert!((f.2 - 30.0).abs() < 1e-9 && f.3 == 0.0 && (f.4 - 20.0).abs() < 1e-3, "{f:?}");
        }
        assert_eq!(
            c.problems[0].to_string(),
            "mirror 0: track: 30.000 mm (48000 steps) is outside its travel 0.00 … 20.00 mm \
             (0 … 32000 steps)"
        );
        // A tilt of at most 3°: the two outer rings (4.3° and 6.4°) are
        // beyond it, the two inner ones (0.8° and 2.5°) within.
        let mut axes = protocol::default_axes();
        axes[2].max_steps = (3.0 * axes[2].steps_per_unit) as i32;
        let c = g.check_design_on(&axes);
        let found: Vec<usize> = out_of_travel(&c)
            .iter()
            .inspect(|f| assert_eq!(f.1, protocol::Axis::Tilt))
            .map(|f| f.0)
            .collect();
        let steep: Vec<usize> =
            c.mirrors.iter().filter(|m| m.axes.unwrap().tilt_deg > 3.0).map(|m| m.mirror).collect();
        assert_eq!(found, steep);
        assert_eq!(steep.len(), 27);
        // The disk turns without end: no angle is beyond it, and the
        // default axes hold every mirror (the test above).
        let mut axes = protocol::default_axes();
        axes[0].max_steps = 10;
        assert_eq!(g.check_design_on(&axes).problems, []);
    }

    #[test]
    fn faults_of_a_design_are_named() {
        let base = ScannerGeometry::default_scanner();
        // A mirror too small: the camera sees past its edge and it lights
        // only the middle of the sample.
        let mut g = base.clone();
        g.mirrors[7].size_mm = 12.0;
        let c = g.check_design();
        assert!(c.problems.iter().any(|p| matches!(p, DesignProblem::ViewCut { mirror: 7, .. })));
        assert!(
            c.problems
                .iter()
                .any(|p| matches!(p, DesignProblem::PartlyLit { mirror: 7, lit } if *lit < 1.0))
        );
        assert!(
            c.problems.iter().all(|p| p.to_string().starts_with("mirror 7:")),
            "{:?}",
            c.problems
        );
        // A narrower beam: the sample's corners in its soft edge, which
        // the white target calibrates out (a warning, not a problem).
        let mut g = base.clone();
        g.source.beam_radius_mm = 20.0;
        let c = g.check_design();
        assert_eq!(c.problems, []);
        assert!(!c.warnings.is_empty());
        for w in &c.warnings {
            assert!(matches!(w, DesignProblem::PartlyLit { lit, .. } if *lit > 0.0 && *lit < 1.0));
        }
        // A beam wide enough to light the neighbours too.
        let mut g = base.clone();
        g.source.beam_radius_mm = 60.0;
        let c = g.check_design();
        assert!(
            c.problems.iter().any(|p| matches!(p, DesignProblem::StrayLight { .. })),
            "{:?}",
            c.problems
        );
        // A sensor too small for the outer ring.
        let mut g = base.clone();
        g.camera.width = 2800;
        g.camera.principal_px[0] = 1400.0;
        let c = g.check_design();
        let off: Vec<usize> = c
            .problems
            .iter()
            .filter_map(|p| match p {
                DesignProblem::OffSensor { mirror, .. } => Some(*mirror),
                _ => None,
            })
            .collect();
        assert!(!off.is_empty() && off.iter().all(|&m| m >= 13), "{off:?}");
        // A mirror turned by 4° about its vertical edge: the camera would
        // see the sample beyond its edge, and its light misses the sample.
        let mut g = base.clone();
        let m = &mut g.mirrors[14];
        let (n, _, v) = m.frame();
        let turned = (n * 4f64.to_radians().cos() + v * 4f64.to_radians().sin()).normalize();
        m.normal = turned.to_array();
        let c = g.check_design();
        assert!(c.problems.iter().any(|p| matches!(p, DesignProblem::ViewCut { mirror: 14, .. })));
        assert!(c.problems.contains(&DesignProblem::PartlyLit { mirror: 14, lit: 0.0 }));
        // A sample larger than the mirrors were laid out for: its views
        // crowd each other (and the mirrors are too small for it).
        let mut g = base.clone();
        g.sample.size_mm = 80.0;
        let c = g.check_design();
        assert!(
            c.problems.iter().any(|p| matches!(p, DesignProblem::ViewsTooClose { .. })),
            "{:?}",
            c.problems
        );
        assert!(c.closest_views.unwrap().2 < g.view_margin_px());
        // A mirror in the beam's way: a copy of mirror 0 halfway along its
        // light path shades it and blocks its view.
        let mut g = base.clone();
        let beam = g.beam(g.mirror_axes(0).unwrap());
        let (_, hit) = g.first_mirror(beam.origin, beam.dir).unwrap();
        let mut blocker = g.mirrors[0].clone();
        blocker.center_mm = ((beam.origin + hit) / 2.0).to_array();
        g.mirrors.push(blocker);
        let c = g.check_design();
        assert!(
            c.problems.iter().any(|p| matches!(p, DesignProblem::Unlit { mirror: 0, reason } if reason.contains("mirror 40"))),
            "{:?}",
            c.problems
        );
    }
}
