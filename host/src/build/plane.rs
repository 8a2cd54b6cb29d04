//! Single-channel float images and the sampling filters the builder uses.

/// A single-channel float image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// `width × height` values.
    pub data: Vec<f32>,
}

/// The four pixels (row-major indices into a `width` × `height` image)
/// and weights of a bilinear read at continuous `p`, pixel centres at
/// half-integers, clamped to the edge: the builder's one formula for
/// reading an image between its pixels.
#[inline]
pub fn bilinear_taps(width: usize, height: usize, p: [f64; 2]) -> ([usize; 4], [f64; 4]) {
    let (fx, fy) = (p[0] - 0.5, p[1] - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (tx, ty) = (fx - x0, fy - y0);
    let column = |x: f64| (x as isize).clamp(0, width as isize - 1) as usize;
    let row = |y: f64| (y as isize).clamp(0, height as isize - 1) as usize * width;
    let (a, b) = (column(x0), column(x0 + 1.0));
    let (c, d) = (row(y0), row(y0 + 1.0));
    (
        [c + a, c + b, d + a, d + b],
        [(1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty],
    )
}

/// `pixels` (row-major, `width` wide) read at `p` ([`bilinear_taps`]).
#[inline]
pub fn bilinear<T: Copy + Into<f64>>(pixels: &[T], width: usize, p: [f64; 2]) -> f64 {
    let (i, w) = bilinear_taps(width, pixels.len() / width, p);
    (0..4).map(|k| pixels[i[k]].into() * w[k]).sum()
}

impl Plane {
    /// A plane of zeros.
    pub fn new(width: usize, height: usize) -> Plane {
        Plane { width, height, data: vec![0.0; width * height] }
    }

    /// Value at integer (x, y), clamped to the edge.
    #[inline]
    pub fn at(&self, x: isize, y: isize) -> f32 {
        let x = x.clamp(0, self.width as isize - 1) as usize;
        let y = y.clamp(0, self.height as isize - 1) as usize;
        self.data[y * self.width + x]
    }

    /// Bilinear sample at continuous (x, y), pixel centres at half-integers.
    #[inline]
    pub fn bilinear(&self, x: f64, y: f64) -> f64 {
        bilinear(&self.data, self.width, [x, y])
    }

    /// Separable Gaussian blur (σ in px), edges clamped.
    pub fn blurred(&self, sigma: f64) -> Plane {
        let r = (3.0 * sigma).ceil() as isize;
        let k: Vec<f64> =
            (-r..=r).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp()).collect();
        let ks: f64 = k.iter().sum();
        let k: Vec<f32> = k.iter().map(|v| (v / ks) as f32).collect();
        let mut tmp = Plane::new(self.width, self.height);
        for y in 0..self.height {
            for x in 0..self.width {
                let mut s = 0.0;
                for (i, w) in k.iter().enumerate() {
                    s += w * self.at(x as isize + i as isize - r, y as isize);
                }
                tmp.data[y * self.width + x] = s;
            }
        }
        let mut out = Plane::new(self.width, self.height);
        for y in 0..self.height {
            for x in 0..self.width {
                let mut s = 0.0;
                for (i, w) in k.iter().enumerate() {
                    s += w * tmp.at(x as isize, y as isize + i as isize - r);
                }
                out.data[y * self.width + x] = s;
            }
        }
        out
    }

    /// The window [x0, x0 + w) × [y0, y0 + h) (clamped reads outside).
    pub fn crop(&self, x0: isize, y0: isize, w: usize, h: usize) -> Plane {
        let mut out = Plane::new(w, h);
        for y in 0..h {
            for x in 0..w {
                out.data[y * w + x] = self.at(x0 + x as isize, y0 + y as isize);
            }
        }
        out
    }
}

/// uv of cell `t` (row-major) of an n × n grid over [0, 1]²: its centre.
#[inline]
pub fn cell_uv(t: usize, n: usize) -> [f64; 2] {
    [((t % n) as f64 + 0.5) / n as f64, ((t / n) as f64 + 0.5) / n as f64]
}

/// Bilinear taps along one axis of `n` cells over [0, 1] (cell centres at
/// (i + ½)/n, clamped at the ends): (first cell, second cell, weight of
/// the second).
#[inline]
pub fn cell_taps(n: usize, u: f64) -> (usize, usize, f64) {
    let x = (u * n as f64 - 0.5).clamp(0.0, n as f64 - 1.0);
    let i = x.floor() as usize;
    (i, (i + 1).min(n - 1), x - i as f64)
}

/// Catmull–Rom weights for fractional offset `t` ∈ [0, 1) (taps −1 … 2).
#[inline]
pub fn catmull_rom(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}
