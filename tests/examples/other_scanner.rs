//! Write the test scanner other than the default (`tests::other_scanner`:
//! 24 mirrors on three rings, a 4:3 sensor) as a geometry file, and print
//! where each mirror shows the sample on the sensor.
//!
//! `cargo run --release -p tests --example other_scanner -- OUT.toml`, then
//! e.g. `scanner demo --geometry OUT.toml --bin 3`.

fn main() {
    let out = std::env::args().nth(1).expect("usage: other_scanner OUT.toml");
    let g = tests::other_scanner();
    for l in 0..g.mirrors.len() {
        let c = g.sample_image_corners(l).expect("the sample in view");
        let (xs, ys): (Vec<f64>, Vec<f64>) = c.iter().map(|p| (p[0], p[1])).unzip();
        let span = |v: &[f64]| {
            (v.iter().copied().fold(f64::MAX, f64::min), v.iter().copied().fold(f64::MIN, f64::max))
        };
        let ((x0, x1), (y0, y1)) = (span(&xs), span(&ys));
        println!("mirror {l:2}: x {x0:7.1} … {x1:7.1}, y {y0:7.1} … {y1:7.1}");
    }
    std::fs::write(&out, g.to_toml()).expect("written");
    eprintln!("{out}: geometry {}", g.hash());
}
