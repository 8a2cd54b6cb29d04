//! The little dense linear algebra the builder needs: symmetric
//! positive-definite solves (Cholesky) for normal equations, the
//! eigenvectors of a small symmetric matrix (cyclic Jacobi: the detail
//! layer's light components, a Gram matrix of one row per light), and plane
//! homographies (normalised DLT, then Gauss–Newton on the reprojection
//! error).

/// Solve `A x = b` for a symmetric positive-definite `n × n` matrix `a`
/// (row-major); `None` if it is not positive definite.
pub fn solve_spd(n: usize, a: &[f64], b: &[f64]) -> Option<Vec<f64>> {
    debug_assert_eq!(a.len(), n * n);
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if s.is_nan() || s <= 0.0 || !s.is_finite() {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i * n + k] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let mut s = y[i];
        for k in i + 1..n {
            s -= l[k * n + i] * x[k];
        }
        x[i] = s / l[i * n + i];
    }
    Some(x)
}

/// Eigenvalues and unit eigenvectors of a symmetric `n × n` matrix `a`
/// (row-major), by cyclic Jacobi rotations: `(values, vectors)` with
/// `vectors[i]` belonging to `values[i]`, largest value first. O(n³) a
/// sweep, for the small matrices it serves (n ≤ a few hundred).
pub fn symmetric_eigen(n: usize, a: &[f64]) -> (Vec<f64>, Vec<Vec<f64>>) {
    debug_assert_eq!(a.len(), n * n);
    let mut a = a.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let scale = a.iter().map(|x| x * x).sum::<f64>();
    for _sweep in 0..64 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j] * a[i * n + j])
            .sum();
        if off <= 1e-30 * scale || off.is_nan() {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                // The rotation that zeroes a[p][q] (Golub & Van Loan, 8.5.2).
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| a[j * n + j].total_cmp(&a[i * n + i]));
    let values = order.iter().map(|&i| a[i * n + i]).collect();
    let vectors = order.iter().map(|&i| (0..n).map(|k| v[k * n + i]).collect()).collect();
    (values, vectors)
}

/// Accumulates the normal equations JᵀJ δ = −Jᵀr of a least-squares problem.
#[derive(Debug, Clone)]
pub struct Normal {
    /// Unknowns.
    pub n: usize,
    /// JᵀJ, row-major.
    pub jtj: Vec<f64>,
    /// Jᵀr.
    pub jtr: Vec<f64>,
    /// Σ r².
    pub cost: f64,
}

impl Normal {
    /// Empty system with `n` unknowns.
    pub fn new(n: usize) -> Normal {
        Normal { n, jtj: vec![0.0; n * n], jtr: vec![0.0; n], cost: 0.0 }
    }

    /// Add one residual `r` with gradient `j` (dense).
    pub fn add(&mut self, j: &[f64], r: f64) {
        self.add_sparse(
            &j.iter().copied().enumerate().filter(|x| x.1 != 0.0).collect::<Vec<_>>(),
            r,
        );
    }

    /// Add one residual with the non-zero entries `(index, value)` of its gradient.
    pub fn add_sparse(&mut self, j: &[(usize, f64)], r: f64) {
        for &(a, ja) in j {
            self.jtr[a] += ja * r;
            for &(b, jb) in j {
                self.jtj[a * self.n + b] += ja * jb;
            }
        }
        self.cost += r * r;
    }

    /// The step δ of Levenberg–Marquardt with damping `lambda`.
    pub fn step(&self, lambda: f64) -> Option<Vec<f64>> {
        let mut a = self.jtj.clone();
        for i in 0..self.n {
            a[i * self.n + i] += lambda * (self.jtj[i * self.n + i] + 1e-12);
        }
        let neg: Vec<f64> = self.jtr.iter().map(|v| -v).collect();
        solve_spd(self.n, &a, &neg)
    }
}

/// A plane homography: x' ~ H x, row-major, h\[8\] = 1.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Homography(pub [f64; 9]);

impl Homography {
    /// Map a point.
    #[inline]
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        let h = &self.0;
        let w = h[6] * p[0] + h[7] * p[1] + h[8];
        [(h[0] * p[0] + h[1] * p[1] + h[2]) / w, (h[3] * p[0] + h[4] * p[1] + h[5]) / w]
    }

    /// The 2 × 2 Jacobian of [`apply`](Self::apply) at `p`: [[dx/du, dx/dv], [dy/du, dy/dv]].
    pub fn jacobian(&self, p: [f64; 2]) -> [[f64; 2]; 2] {
        let h = &self.0;
        let w = h[6] * p[0] + h[7] * p[1] + h[8];
        let x = (h[0] * p[0] + h[1] * p[1] + h[2]) / w;
        let y = (h[3] * p[0] + h[4] * p[1] + h[5]) / w;
        [
            [(h[0] - x * h[6]) / w, (h[1] - x * h[7]) / w],
            [(h[3] - y * h[6]) / w, (h[4] - y * h[7]) / w],
        ]
    }

    /// The homography with h\[8\] scaled to 1.
    fn normalised(m: [f64; 9]) -> Option<Homography> {
        (m[8].abs() > 1e-300 && m.iter().all(|v| v.is_finite()))
            .then(|| Homography(m.map(|v| v / m[8])))
    }

    /// The homography mapping `src[i]` to `dst[i]` best (≥ 4 points):
    /// normalised DLT with h33 = 1, then Gauss–Newton on the squared
    /// distances in the destination.
    pub fn fit(src: &[[f64; 2]], dst: &[[f64; 2]]) -> Option<Homography> {
        if src.len() < 4 || src.len() != dst.len() {
            return None;
        }
        let (ts, ss) = similarity(src);
        let (td, sd) = similarity(dst);
        let ns: Vec<[f64; 2]> =
            src.iter().map(|p| [(p[0] - ts[0]) * ss, (p[1] - ts[1]) * ss]).collect();
        let nd: Vec<[f64; 2]> =
            dst.iter().map(|p| [(p[0] - td[0]) * sd, (p[1] - td[1]) * sd]).collect();
        // Linear: h33 = 1, 8 unknowns.
        let mut eq = Normal::new(8);
        for (s, d) in ns.iter().zip(&nd) {
            let (u, v, x, y) = (s[0], s[1], d[0], d[1]);
            eq.add(&[u, v, 1.0, 0.0, 0.0, 0.0, -x * u, -x * v], -x);
            eq.add(&[0.0, 0.0, 0.0, u, v, 1.0, -y * u, -y * v], -y);
        }
        let h = eq.step(0.0)?;
        let mut hn = Homography([h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0]);
        // Geometric refinement in normalised coordinates.
        for _ in 0..10 {
            let mut eq = Normal::new(8);
            for (s, d) in ns.iter().zip(&nd) {
                let g = &hn.0;
                let w = g[6] * s[0] + g[7] * s[1] + 1.0;
                let x = (g[0] * s[0] + g[1] * s[1] + g[2]) / w;
                let y = (g[3] * s[0] + g[4] * s[1] + g[5]) / w;
                let (u, v) = (s[0], s[1]);
                eq.add(&[u / w, v / w, 1.0 / w, 0.0, 0.0, 0.0, -x * u / w, -x * v / w], x - d[0]);
                eq.add(&[0.0, 0.0, 0.0, u / w, v / w, 1.0 / w, -y * u / w, -y * v / w], y - d[1]);
            }
            let Some(dh) = eq.step(1e-9) else { break };
            for (h, d) in hn.0.iter_mut().zip(&dh) {
                *h += d;
            }
            if dh.iter().map(|v| v * v).sum::<f64>() < 1e-24 {
                break;
            }
        }
        // Undo the normalisations: H = Td⁻¹ Hn Ts.
        let ts_m = [ss, 0.0, -ss * ts[0], 0.0, ss, -ss * ts[1], 0.0, 0.0, 1.0];
        let td_inv = [1.0 / sd, 0.0, td[0], 0.0, 1.0 / sd, td[1], 0.0, 0.0, 1.0];
        Homography::normalised(mul3(&mul3(&td_inv, &hn.0), &ts_m))
    }

    /// The unit square's corners (0, 0), (1, 0), (1, 1), (0, 1) mapped: a
    /// view's sample in the frame, px, in order around it.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]].map(|p| self.apply(p))
    }

    /// Bounding box `[x0, y0, x1, y1]` of the unit square's image (a view's
    /// sample in the frame, px).
    pub fn bounds(&self) -> [f64; 4] {
        let pts = self.corners();
        [
            pts.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min),
            pts.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min),
            pts.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max),
            pts.iter().map(|p| p[1]).fold(f64::NEG_INFINITY, f64::max),
        ]
    }

    /// The area of the unit square's image (shoelace over its corners;
    /// positive for either orientation).
    pub fn area(&self) -> f64 {
        let p = self.corners();
        let twice: f64 =
            (0..4).map(|k| p[k][0] * p[(k + 1) % 4][1] - p[(k + 1) % 4][0] * p[k][1]).sum();
        twice.abs() / 2.0
    }

    /// The pixels within `pad` px of the unit square's image, as a frame
    /// window `[x0, y0, x1, y1)` (clamped at 0; the reader clips the rest).
    pub fn window(&self, pad: f64) -> crate::exrio::PixelRect {
        let b = self.bounds();
        let lo = |v: f64| (v - pad).floor().max(0.0) as usize;
        let hi = |v: f64| (v + pad).ceil().max(0.0) as usize + 1;
        [lo(b[0]), lo(b[1]), hi(b[2]), hi(b[3])]
    }

    /// This mapping followed by a shift of `d` (e.g. into a frame window
    /// whose corner is at −d).
    pub fn translated(&self, d: [f64; 2]) -> Homography {
        let m = &self.0;
        Homography([
            m[0] + d[0] * m[6],
            m[1] + d[0] * m[7],
            m[2] + d[0] * m[8],
            m[3] + d[1] * m[6],
            m[4] + d[1] * m[7],
            m[5] + d[1] * m[8],
            m[6],
            m[7],
            m[8],
        ])
    }

    /// This mapping after a scaling by `k` about the point `c` (the
    /// scaling first): `p ↦ self(c + k (p − c))`.
    pub fn after_scaling(&self, k: f64, c: [f64; 2]) -> Homography {
        let a = [k, 0.0, (1.0 - k) * c[0], 0.0, k, (1.0 - k) * c[1], 0.0, 0.0, 1.0];
        Homography(mul3(&self.0, &a))
    }

    /// This mapping after a shift by `d` (the shift first): `p ↦ self(p + d)`.
    pub fn after_shift(&self, d: [f64; 2]) -> Homography {
        Homography(mul3(&self.0, &[1.0, 0.0, d[0], 0.0, 1.0, d[1], 0.0, 0.0, 1.0]))
    }

    /// The inverse mapping.
    pub fn inverse(&self) -> Option<Homography> {
        let m = &self.0;
        let c = [
            m[4] * m[8] - m[5] * m[7],
            m[2] * m[7] - m[1] * m[8],
            m[1] * m[5] - m[2] * m[4],
            m[5] * m[6] - m[3] * m[8],
            m[0] * m[8] - m[2] * m[6],
            m[2] * m[3] - m[0] * m[5],
            m[3] * m[7] - m[4] * m[6],
            m[1] * m[6] - m[0] * m[7],
            m[0] * m[4] - m[1] * m[3],
        ];
        Homography::normalised(c)
    }
}

fn mul3(a: &[f64; 9], b: &[f64; 9]) -> [f64; 9] {
    std::array::from_fn(|k| {
        let (i, j) = (k / 3, k % 3);
        (0..3).map(|t| a[i * 3 + t] * b[t * 3 + j]).sum()
    })
}

/// Centroid and the scale that gives the points a mean distance √2 from it.
fn similarity(p: &[[f64; 2]]) -> ([f64; 2], f64) {
    let n = p.len() as f64;
    let c = [p.iter().map(|q| q[0]).sum::<f64>() / n, p.iter().map(|q| q[1]).sum::<f64>() / n];
    let d =
        p.iter().map(|q| ((q[0] - c[0]).powi(2) + (q[1] - c[1]).powi(2)).sqrt()).sum::<f64>() / n;
    (c, if d > 0.0 { std::f64::consts::SQRT_2 / d } else { 1.0 })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn symmetric_eigen_finds_every_pair() {
        // A = Q diag(d) Qᵀ with a known rotation Q (two of its values equal).
        let n = 5;
        let d = [7.0, 3.0, 3.0, -1.0, 0.5];
        let q: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                let raw: Vec<f64> = (0..n)
                    .map(|k| ((i * 7 + k * 3) as f64 * 0.91).sin() + (i == k) as u8 as f64)
                    .collect();
                raw
            })
            .collect();
        // Orthonormalise the rows (Gram–Schmidt).
        let mut o: Vec<Vec<f64>> = Vec::new();
        for r in q {
            let mut r = r;
            for b in &o {
                let p: f64 = r.iter().zip(b).map(|(x, y)| x * y).sum();
                r.iter_mut().zip(b).for_each(|(x, y)| *x -= p * y);
            }
            let l = r.iter().map(|x| x * x).sum::<f64>().sqrt();
            o.push(r.iter().map(|x| x / l).collect());
        }
        let a: Vec<f64> =
            (0..n * n).map(|ij| (0..n).map(|k| o[k][ij / n] * d[k] * o[k][ij % n]).sum()).collect();
        let (values, vectors) = symmetric_eigen(n, &a);
        let mut want = d.to_vec();
        want.sort_by(|x, y| y.total_cmp(x));
        for (v, w) in values.iter().zip(&want) {
            assert!((v - w).abs() < 1e-10, "{values:?} against {want:?}");
        }
        for (val, vec) in values.iter().zip(&vectors) {
            let len = vec.iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!((len - 1.0).abs() < 1e-10);
            for i in 0..n {
                let av: f64 = (0..n).map(|k| a[i * n + k] * vec[k]).sum();
                assert!((av - val * vec[i]).abs() < 1e-9, "A v ≠ λ v");
            }
        }
        // The largest one's vector is ± the first row of Q.
        let dot: f64 = vectors[0].iter().zip(&o[0]).map(|(x, y)| x * y).sum();
        assert!((dot.abs() - 1.0).abs() < 1e-10);
    }

    #[test]
    fn a_homography_is_recovered_from_its_points_and_inverted() {
        let h = Homography([120.0, 8.0, 900.0, -5.0, 48.0, 1300.0, 0.01, -0.02, 1.0]);
        let src: Vec<[f64; 2]> =
            (0..7).flat_map(|i| (0..7).map(move |j| [i as f64 / 6.0, j as f64 / 6.0])).collect();
        let dst: Vec<[f64; 2]> = src.iter().map(|&p| h.apply(p)).collect();
        let fit = Homography::fit(&src, &dst).unwrap();
        for (s, d) in src.iter().zip(&dst) {
            let p = fit.apply(*s);
            assert!((p[0] - d[0]).abs() < 1e-8 && (p[1] - d[1]).abs() < 1e-8);
        }
        let inv = fit.inverse().unwrap();
        let back = inv.apply(dst[10]);
        assert!((back[0] - src[10][0]).abs() < 1e-10 && (back[1] - src[10][1]).abs() < 1e-10);
        // The Jacobian against finite differences.
        let j = h.jacobian([0.3, 0.6]);
        let e = 1e-6;
        let a = h.apply([0.3 + e, 0.6]);
        let b = h.apply([0.3 - e, 0.6]);
        assert!(((a[0] - b[0]) / (2.0 * e) - j[0][0]).abs() < 1e-4);
        assert!(((a[1] - b[1]) / (2.0 * e) - j[1][0]).abs() < 1e-4);
        // Translated: the same point, shifted.
        let (p, q) = (h.apply([0.3, 0.6]), h.translated([-17.0, 4.5]).apply([0.3, 0.6]));
        let (c, k) = ([0.2, 1.7], 1.25);
        let scaled = h.after_scaling(k, c).apply([0.3, 0.6]);
        let direct = h.apply([c[0] + k * (0.3 - c[0]), c[1] + k * (0.6 - c[1])]);
        assert!((scaled[0] - direct[0]).abs() < 1e-9 && (scaled[1] - direct[1]).abs() < 1e-9);
        assert!((q[0] - (p[0] - 17.0)).abs() < 1e-9 && (q[1] - (p[1] + 4.5)).abs() < 1e-9);
    }

    #[test]
    fn spd_solve() {
        let a = [4.0, 1.0, 1.0, 3.0];
        let x = solve_spd(2, &a, &[1.0, 2.0]).unwrap();
        assert!((4.0 * x[0] + x[1] - 1.0).abs() < 1e-12 && (x[0] + 3.0 * x[1] - 2.0).abs() < 1e-12);
        assert!(solve_spd(2, &[1.0, 2.0, 2.0, 1.0], &[1.0, 1.0]).is_none());
    }
}
