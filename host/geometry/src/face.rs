//! Where the sample's face lies: a plane near the holder's.
//!
//! The targets (checkerboard, white) lie in the holder's plane, sample-local
//! z = 0. A sample thicker than they are, or one that does not lie flat
//! against the holder, has its face elsewhere: its centre `height_mm`
//! towards the mirrors (sample-local +z) and the face tilted, rising by
//! `slope[0]` mm per mm along u (sample-local x) and `slope[1]` along v
//! (sample-local y). The face carries its own frame: its axes are the
//! holder's turned by the least rotation that takes the holder's normal to
//! the face's, and a material's uv and directions are the face's
//! (docs/scanner-geometry.md, "the sample's face").
//!
//! One copy of these formulas serves the simulator, which puts a sample
//! there, and the builder, which reads the region images there.

use glam::{DQuat, DVec3};

/// The sample's face: a plane through (0, 0, `height_mm`), sample-local,
/// with gradient `slope` (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SampleFace {
    /// The face's centre above the holder's plane, towards the mirrors, mm.
    pub height_mm: f64,
    /// The face's rise along u and along v, mm per mm.
    pub slope: [f64; 2],
}

impl SampleFace {
    /// The face in the holder's plane, as the targets.
    pub const FLUSH: SampleFace = SampleFace { height_mm: 0.0, slope: [0.0, 0.0] };

    /// A face parallel to the holder's plane, `height_mm` above it.
    pub fn at_height(height_mm: f64) -> SampleFace {
        SampleFace { height_mm, slope: [0.0; 2] }
    }

    /// A face `height_mm` above the holder's plane, rising along u and v
    /// at the angles `tilt_deg` (degrees; slope = tan).
    pub fn tilted(height_mm: f64, tilt_deg: [f64; 2]) -> SampleFace {
        SampleFace { height_mm, slope: slopes_of(tilt_deg) }
    }

    /// The face's rise along u and v as angles, degrees.
    pub fn tilt_deg_uv(&self) -> [f64; 2] {
        angles_of(self.slope)
    }

    /// Whether the face is the holder's plane.
    pub fn is_flush(&self) -> bool {
        *self == SampleFace::FLUSH
    }

    /// Whether the face is parallel to the holder's plane.
    pub fn is_level(&self) -> bool {
        self.slope == [0.0; 2]
    }

    /// The face's unit normal, sample-local (towards the mirrors).
    pub fn normal(&self) -> DVec3 {
        DVec3::new(-self.slope[0], -self.slope[1], 1.0).normalize()
    }

    /// The angle between the face's normal and the holder's, degrees.
    pub fn tilt_deg(&self) -> f64 {
        self.normal().z.clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// The rotation from the holder's frame to the face's (the least one
    /// taking +z to [`Self::normal`]).
    fn rotation(&self) -> DQuat {
        DQuat::from_rotation_arc(DVec3::Z, self.normal())
    }

    /// The face's axes along u and v and its normal, sample-local.
    pub fn axes(&self) -> [DVec3; 3] {
        let q = self.rotation();
        [q * DVec3::X, q * DVec3::Y, q * DVec3::Z]
    }

    /// The face's point at material uv, sample-local mm from the holder's
    /// centre, for a sample `size_mm` wide (uv (0.5, 0.5) at the face's
    /// centre; uv measured along the face).
    pub fn point(&self, size_mm: f64, uv: [f64; 2]) -> DVec3 {
        let [eu, ev, _] = self.axes();
        DVec3::new(0.0, 0.0, self.height_mm)
            + eu * ((uv[0] - 0.5) * size_mm)
            + ev * ((uv[1] - 0.5) * size_mm)
    }

    /// The material uv of sample-local point `p` (on the face), for a
    /// sample `size_mm` wide.
    pub fn uv(&self, size_mm: f64, p: DVec3) -> [f64; 2] {
        let [eu, ev, _] = self.axes();
        let d = p - DVec3::new(0.0, 0.0, self.height_mm);
        [d.dot(eu) / size_mm + 0.5, d.dot(ev) / size_mm + 0.5]
    }

    /// Sample-local direction `d` in the face's own frame (the frame a
    /// material's directions are in).
    pub fn to_face(&self, d: DVec3) -> DVec3 {
        let [eu, ev, n] = self.axes();
        DVec3::new(d.dot(eu), d.dot(ev), d.dot(n))
    }

    /// Direction `d` in the face's own frame, sample-local (the inverse of
    /// [`Self::to_face`]).
    pub fn from_face(&self, d: DVec3) -> DVec3 {
        let [eu, ev, n] = self.axes();
        eu * d.x + ev * d.y + n * d.z
    }

    /// Sample-local point `p` as seen from the face: relative to its centre,
    /// in its frame.
    pub fn to_face_point(&self, p: DVec3) -> DVec3 {
        self.to_face(p - DVec3::new(0.0, 0.0, self.height_mm))
    }

    /// Where the ray from `origin` along `dir` (sample-local) meets the
    /// face's plane, if ahead of `origin` and not grazing it.
    pub fn intersect(&self, origin: DVec3, dir: DVec3) -> Option<DVec3> {
        let n = self.normal();
        let across = n.dot(dir);
        if across.abs() < 1e-12 {
            return None;
        }
        let t = n.dot(DVec3::new(0.0, 0.0, self.height_mm) - origin) / across;
        (t > 0.0).then(|| origin + dir * t)
    }

    /// The holder's-plane uv where the line from `origin` (sample-local
    /// mm, off the holder's plane: a virtual camera) through the face's
    /// point at material uv crosses the holder's plane, for a sample
    /// `size_mm` wide: what the calibration's homography of the view from
    /// `origin` maps for that point.
    pub fn holder_uv_from(&self, size_mm: f64, uv: [f64; 2], origin: DVec3) -> [f64; 2] {
        let p = self.point(size_mm, uv);
        let q = origin + (p - origin) * (origin.z / (origin.z - p.z));
        SampleFace::FLUSH.uv(size_mm, q)
    }

    /// The face's height above the holder's plane at sample-local (x, y),
    /// mm.
    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        self.height_mm + self.slope[0] * x + self.slope[1] * y
    }
}

/// The outward normals of the face's edges 0…3 (0: v = 0, 1: u = 1,
/// 2: v = 1, 3: u = 0) in the face's frame (x along u, y along v): the
/// sides below them face that way.
pub const EDGE_NORMALS: [[f64; 2]; 4] = [[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]];

/// Angles (degrees) as slopes (their tangents).
pub fn slopes_of(deg: [f64; 2]) -> [f64; 2] {
    deg.map(|t| t.to_radians().tan())
}

/// Slopes as angles, degrees (also their uncertainties, to first order).
pub fn angles_of(slope: [f64; 2]) -> [f64; 2] {
    slope.map(|s| s.atan().to_degrees())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The face's frame: orthonormal, its normal the plane's, its points on
    /// the plane, uv and points inverse, and a flush face the identity.
    #[test]
    fn the_face_frame_is_consistent() {
        let f = SampleFace { height_mm: 0.4, slope: [0.02, -0.035] };
        let [eu, ev, n] = f.axes();
        assert!((eu.dot(ev)).abs() < 1e-12 && (eu.dot(n)).abs() < 1e-12);
        assert!((eu.length() - 1.0).abs() < 1e-12 && (n - f.normal()).length() < 1e-12);
        for uv in [[0.0, 0.0], [1.0, 0.3], [0.7, 1.0]] {
            let p = f.point(25.4, uv);
            assert!((p.z - f.height_at(p.x, p.y)).abs() < 1e-12, "{p}");
            let back = f.uv(25.4, p);
            assert!((back[0] - uv[0]).abs() < 1e-12 && (back[1] - uv[1]).abs() < 1e-12);
        }
        // The face rises along +u by its slope: e_u leans up.
        assert!(eu.z > 0.0 && ev.z < 0.0);
        // A ray straight down from above hits the plane at its height.
        let hit = f.intersect(DVec3::new(3.0, -2.0, 100.0), -DVec3::Z).unwrap();
        assert!((hit.z - f.height_at(3.0, -2.0)).abs() < 1e-12);
        assert!((f.tilt_deg() - (0.02f64.hypot(0.035)).atan().to_degrees()).abs() < 1e-9);
        let d = DVec3::new(0.3, -0.2, 0.9).normalize();
        assert!((SampleFace::FLUSH.to_face(d) - d).length() < 1e-15);
        assert!((f.to_face(f.normal()) - DVec3::Z).length() < 1e-12);
    }

    /// A view from a point sees the face's point at uv where its ray
    /// crosses the holder's plane: that crossing, the point and the origin
    /// lie on one line, and a flush face's point is its own.
    #[test]
    fn the_holder_plane_point_seen_from_a_point() {
        let f = SampleFace { height_mm: 5.0, slope: [0.02, -0.035] };
        let origin = DVec3::new(300.0, -500.0, 900.0);
        for uv in [[0.0, 0.0], [1.0, 0.3], [0.5, 0.5]] {
            let q = SampleFace::FLUSH.point(25.4, f.holder_uv_from(25.4, uv, origin));
            let p = f.point(25.4, uv);
            assert!(
                q.z == 0.0
                    && (q - origin).normalize().cross((p - origin).normalize()).length() < 1e-12
            );
            let flush = SampleFace::FLUSH.holder_uv_from(25.4, uv, origin);
            assert!((flush[0] - uv[0]).abs() < 1e-12 && (flush[1] - uv[1]).abs() < 1e-12);
        }
    }
}
