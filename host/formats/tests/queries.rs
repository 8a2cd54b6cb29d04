//! Query and answer files: round trips in both encodings, files written by
//! NumPy's own layout rules, and refusals that name what is wrong.

use std::path::Path;

use scanner_formats::queries::*;

fn sample_queries() -> Vec<Query> {
    (0..7)
        .map(|i| {
            let t = i as f64 * 0.37;
            let wi = [t.sin() * 0.5, t.cos() * 0.5, (1.0f64 - 0.25).sqrt()];
            Query { uv: [0.1 * i as f64, 1.0 - 0.13 * i as f64], wi, wo: [0.0, 0.6, 0.8] }
        })
        .collect()
}

#[test]
fn queries_and_answers_round_trip_in_both_encodings() {
    let dir = tempfile::tempdir().unwrap();
    let q = sample_queries();
    for name in ["q.npy", "q.csv"] {
        let path = dir.path().join(name);
        write_queries(&path, &q).unwrap();
        let back = read_queries(&path).unwrap();
        assert_eq!(back.len(), q.len());
        for (a, b) in back.iter().zip(&q) {
            for (x, y) in a.to_row().iter().zip(b.to_row()) {
                assert!((x - y).abs() < 1e-15, "{name}: {x} vs {y}");
            }
        }
    }
    let answers: Vec<[f32; 3]> = (0..5).map(|i| [i as f32 * 0.1, 1.5e-7, 42.0]).collect();
    for name in ["a.npy", "a.csv"] {
        let path = dir.path().join(name);
        write_answers(&path, &answers).unwrap();
        assert_eq!(read_answers(&path).unwrap(), answers, "{name}");
    }
}

/// A .npy file laid out by hand as NumPy writes it: version 1.0 header.
fn npy_bytes(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut header = format!(
        "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
        if fortran { "True" } else { "False" }
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

#[test]
fn float32_and_fortran_order_npy_files_are_read_and_directions_normalised() {
    let dir = tempfile::tempdir().unwrap();
    let rows =
        [[0.25f32, 0.5, 0.0, 0.0, 2.0, 3.0, 0.0, 4.0], [1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0]];
    let c: Vec<f32> = rows.iter().flatten().copied().collect();
    let path = dir.path().join("c.npy");
    std::fs::write(&path, npy_bytes("<f4", false, "(2, 8)", &f32_bytes(&c))).unwrap();
    let q = read_queries(&path).unwrap();
    assert_eq!(q[0].uv, [0.25, 0.5]);
    assert_eq!(q[0].wi, [0.0, 0.0, 1.0]);
    assert_eq!(q[0].wo, [0.6, 0.0, 0.8]);
    let s = std::f64::consts::FRAC_1_SQRT_2;
    assert!((q[1].wi[1] - s).abs() < 1e-12 && (q[1].wi[2] - s).abs() < 1e-12);
    // The same array in Fortran (column-major) order.
    let f: Vec<f32> = (0..8).flat_map(|k| rows.iter().map(move |r| r[k])).collect();
    let path = dir.path().join("f.npy");
    std::fs::write(&path, npy_bytes("<f4", true, "(2, 8)", &f32_bytes(&f))).unwrap();
    assert_eq!(read_queries(&path).unwrap(), q);
}

#[test]
fn huge_and_tiny_finite_directions_are_normalised_without_overflow() {
    let q = Query::from_row([0.5, 0.5, 1e200, 0.0, 1e200, 0.0, 3e300, 4e300], 0).unwrap();
    let s = std::f64::consts::FRAC_1_SQRT_2;
    assert!((q.wi[0] - s).abs() < 1e-15 && (q.wi[2] - s).abs() < 1e-15, "{q:?}");
    assert!((q.wo[1] - 0.6).abs() < 1e-15 && (q.wo[2] - 0.8).abs() < 1e-15, "{q:?}");
    let q = Query::from_row([0.5, 0.5, 0.0, 0.0, 2e-6, 0.0, 1e-6, 1e-6], 0).unwrap();
    assert_eq!(q.wi, [0.0, 0.0, 1.0]);
    assert!((q.wo[1] - s).abs() < 1e-15, "{q:?}");
    assert!(Query::from_row([0.5, 0.5, 0.0, 0.0, 1e-7, 0.0, 0.0, 1.0], 0).is_err());
}

fn refused(path: &Path) -> String {
    read_queries(path).unwrap_err().to_string()
}

#[test]
fn bad_query_files_are_refused_with_their_reason() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let write = |n: &str, b: &[u8]| std::fs::write(dir.path().join(n), b).unwrap();
    write("cols.csv", b"u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_q\n0,0,0,0,1,0,0,1\n");
    assert!(refused(&p("cols.csv")).contains("unknown column \"wo_q\""));
    write("missing.csv", b"u,v,wi_x,wi_y,wi_z,wo_x,wo_y\n0,0,0,0,1,0,0\n");
    assert!(refused(&p("missing.csv")).contains("missing column \"wo_z\""));
    write("nan.csv", b"u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_z\n0,0,0,0,1,0,0,1\n0,0,NaN,0,1,0,0,1\n");
    assert!(refused(&p("nan.csv")).contains("row 1: wi_x is NaN"));
    write("zero.csv", b"u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_z\n0,0,0,0,1,0,0,0\n");
    assert!(refused(&p("zero.csv")).contains("row 0: wo is a zero vector"));
    write("text.csv", b"u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_z\n0,0,0,0,up,0,0,1\n");
    assert!(refused(&p("text.csv")).contains("wi_z: \"up\" is not a number"));
    write("short.csv", b"u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_z\n0,0,0,0,1,0,0\n");
    assert!(refused(&p("short.csv")).contains("short.csv"));
    let seven = vec![0u8; 7 * 4];
    write("shape.npy", &npy_bytes("<f4", false, "(1, 7)", &seven));
    assert!(refused(&p("shape.npy")).contains("shape [1, 7], expected (N, 8)"));
    write("int.npy", &npy_bytes("<i4", false, "(1, 8)", &[0u8; 32]));
    assert!(refused(&p("int.npy")).contains("expected float32 or float64"));
    write("trunc.npy", &npy_bytes("<f8", false, "(2, 8)", &[0u8; 64]));
    assert!(refused(&p("trunc.npy")).contains("trunc.npy"));
    // A forged row count: refused before anything is allocated for it.
    for (shape, reason) in [
        ("(1000000000000000, 8)", "needs more data than the file's 192 bytes"),
        ("(1152921504606846976, 8)", "needs more data than the file's 192 bytes"),
        ("(4611686018427387904, 8)", "shape has more elements than any file can hold"),
    ] {
        write("forged.npy", &npy_bytes("<f8", false, shape, &[0u8; 64]));
        assert!(
            refused(&p("forged.npy")).contains(reason),
            "{shape}: {}",
            refused(&p("forged.npy"))
        );
    }
    // Nested brackets, which npyz's header parser takes exponential time
    // over (found by the fuzz target): refused at once.
    let nested = format!("{}0{}", "{'a':".repeat(40), "}".repeat(40));
    let mut bytes = npy_bytes("<f8", false, "(0, 8)", &[]);
    let header = format!("{nested}\n");
    bytes.truncate(8);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    write("nested.npy", &bytes);
    assert!(refused(&p("nested.npy")).contains("not one flat dictionary"));
    write("structured.npy", &npy_bytes("[('x', '<f8')]", false, "(1, 8)", &[0u8; 64]));
    assert!(refused(&p("structured.npy")).contains("not one flat dictionary"));
    write("junk.npy", b"not numpy at all");
    assert!(refused(&p("junk.npy")).contains("not a .npy file"));
    assert!(refused(&p("q.txt")).contains("unknown file type"));
    assert!(matches!(read_queries(&p("absent.csv")), Err(QueryError::Io { .. })));
}
