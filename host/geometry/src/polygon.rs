//! Convex polygons of a few vertices, clipped by half-planes: how much of
//! a pixel's square lies on the sample (the region images' straddling
//! pixels, the simulator's outline pixels).

/// A convex polygon of at most 8 vertices (a quadrilateral clipped by up
/// to four half-planes: each clip adds at most one vertex), in order
/// around it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Polygon {
    v: [[f64; 2]; 8],
    len: usize,
}

impl Polygon {
    /// The quadrilateral `q` (its vertices in order around it).
    pub fn quad(q: [[f64; 2]; 4]) -> Polygon {
        let mut v = [[0.0; 2]; 8];
        v[..4].copy_from_slice(&q);
        Polygon { v, len: 4 }
    }

    /// The unit pixel square centred at `p`.
    pub fn pixel(p: [f64; 2]) -> Polygon {
        Polygon::quad([
            [p[0] - 0.5, p[1] - 0.5],
            [p[0] + 0.5, p[1] - 0.5],
            [p[0] + 0.5, p[1] + 0.5],
            [p[0] - 0.5, p[1] + 0.5],
        ])
    }

    /// Whether nothing is left.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The part where the affine function `f` is ≥ 0 (Sutherland–Hodgman).
    pub fn clip(&self, f: impl Fn([f64; 2]) -> f64) -> Polygon {
        let mut out = Polygon { v: [[0.0; 2]; 8], len: 0 };
        for i in 0..self.len {
            let (a, b) = (self.v[i], self.v[(i + 1) % self.len]);
            let (fa, fb) = (f(a), f(b));
            if fa >= 0.0 && out.len < 8 {
                out.v[out.len] = a;
                out.len += 1;
            }
            if (fa >= 0.0) != (fb >= 0.0) && out.len < 8 {
                let t = fa / (fa - fb);
                out.v[out.len] = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                out.len += 1;
            }
        }
        out
    }

    /// Its area (shoelace).
    pub fn area(&self) -> f64 {
        let mut twice = 0.0;
        for i in 0..self.len {
            let (a, b) = (self.v[i], self.v[(i + 1) % self.len]);
            twice += a[0] * b[1] - a[1] * b[0];
        }
        0.5 * twice.abs()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pixel clipped by a line through it keeps the part on the line's
    /// side; a quadrilateral clipped to a square keeps their overlap.
    #[test]
    fn clipped_areas() {
        let p = Polygon::pixel([10.5, 20.5]);
        assert!((p.area() - 1.0).abs() < 1e-12);
        assert!((p.clip(|q| q[0] - 10.3).area() - 0.7).abs() < 1e-12);
        // A diagonal cut through the centre halves it.
        assert!((p.clip(|q| (q[0] - 10.5) + (q[1] - 20.5)).area() - 0.5).abs() < 1e-12);
        // A corner cut: the triangle beyond x + y = 1 about the centre,
        // legs ½.
        let corner = p.clip(|q| (q[0] - 10.5) + (q[1] - 20.5) - 0.5);
        assert!((corner.area() - 0.125).abs() < 1e-12, "{}", corner.area());
        assert!(p.clip(|q| q[0] - 12.0).is_empty());
        // The diamond |x| + |y| ≤ ¾ over the unit square around the origin:
        // the square less four corner triangles of legs ¼.
        let diamond = Polygon::quad([[0.75, 0.0], [0.0, 0.75], [-0.75, 0.0], [0.0, -0.75]]);
        let mut on = diamond;
        for (axis, sign) in [(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)] {
            on = on.clip(|q: [f64; 2]| 0.5 - sign * q[axis]);
        }
        assert!((on.area() - (1.0 - 4.0 * 0.03125)).abs() < 1e-12, "{}", on.area());
    }
}
