//! The C API from C: `examples/shade.c` compiled against
//! `include/scanner_shading.h` with the system's C compiler (`cc`, the one
//! Rust itself links with; `$CC` overrides) and linked with this crate's
//! shared library answers every query exactly as `Material::eval` does, on
//! files of every kind; bad files give a status and a message naming them.
//! Then the exported functions called directly: null pointers, short
//! buffers, many threads on one handle.

use std::ffi::{CStr, CString, c_char};
use std::path::{Path, PathBuf};
use std::process::Command;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scanner_shading::{Interpolation, Material, MaterialData, ShadeQuery};
use scanner_shading_c::*;

#[path = "../../benches/support/synthetic.rs"]
mod synthetic;

use synthetic::{Shape, synthetic, with_detail, with_texel_model};

/// Material files of every kind the format has: (name, content).
fn materials() -> Vec<(&'static str, MaterialData)> {
    let shape = Shape { mirrors: 12, resolution: 16, colours: 16, lights_per_index: 2 };
    vec![
        ("default", synthetic(&shape, Interpolation::Default, 0.5, 1)),
        ("unshifted", synthetic(&shape, Interpolation::Default, 0.0, 2)),
        (
            "texel-detail",
            with_detail(
                with_texel_model(synthetic(&shape, Interpolation::Default, 0.5, 3), 4),
                2,
                5,
            ),
        ),
        (
            "patent",
            synthetic(&shape, Interpolation::Patent { columns: 64, rows: 16, points: 200 }, 0.5, 6),
        ),
    ]
}

/// Queries over the whole hemisphere and beyond: uv outside [0, 1]² (it
/// wraps), non-unit directions, runs sharing their directions (the
/// batch's reuse), a captured pair, below the horizon, zero and NaN.
fn queries(m: &Material) -> Vec<ShadeQuery> {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let dir = |rng: &mut ChaCha8Rng| -> [f32; 3] {
        let z: f32 = rng.random_range(0.02..1.0);
        let phi: f32 = rng.random_range(0.0..std::f32::consts::TAU);
        let r = (1.0 - z * z).sqrt();
        let scale = rng.random_range(0.5..3.0);
        [r * phi.cos() * scale, r * phi.sin() * scale, z * scale]
    };
    let mut q = Vec::new();
    for _ in 0..60 {
        let (wi, wo) = (dir(&mut rng), dir(&mut rng));
        for _ in 0..rng.random_range(1..5) {
            q.push(ShadeQuery { uv: [rng.random_range(-0.5..1.5), rng.random()], wi, wo });
        }
    }
    let meta = m.metadata();
    let (l, v) = (meta.lights[1].direction, meta.views[2].direction);
    let captured = ShadeQuery { uv: [0.3, 0.7], wi: l.map(|x| x as f32), wo: v.map(|x| x as f32) };
    q.push(captured);
    q.push(ShadeQuery { wi: [0.3, 0.1, -0.2], ..captured });
    q.push(ShadeQuery { wo: [0.0; 3], ..captured });
    q.push(ShadeQuery { uv: [f32::NAN, 0.5], ..captured });
    q.push(ShadeQuery { wi: [f32::NAN, 0.0, 1.0], ..captured });
    q
}

/// The directory of this crate's shared library: the test binary's own
/// (`target/<profile>/deps`), where Cargo builds it for the tests.
fn library_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let deps = exe.parent().unwrap().to_path_buf();
    let name = format!(
        "{}scanner_shading_c{}",
        std::env::consts::DLL_PREFIX,
        std::env::consts::DLL_SUFFIX
    );
    assert!(deps.join(&name).exists(), "{name} is not in {}", deps.display());
    deps
}

/// `examples/shade.c` compiled into `dir`, linked with the shared library.
fn compile(dir: &Path) -> PathBuf {
    let lib = library_dir();
    let exe = dir.join("shade");
    let mut link = vec!["-L".into(), lib.display().to_string(), "-lscanner_shading_c".into()];
    link.push(format!("-Wl,-rpath,{}", lib.display()));
    cc(&exe, &link);
    exe
}

/// `examples/shade.c` compiled into `dir`, linked with the static library
/// and the native libraries Rust's standard library needs, as rustc
/// lists them (`--print native-static-libs`).
fn compile_static(dir: &Path) -> PathBuf {
    let archive = library_dir().join("libscanner_shading_c.a");
    assert!(archive.exists(), "{} is not built", archive.display());
    let exe = dir.join("shade-static");
    let mut link = vec![archive.display().to_string()];
    link.extend(native_static_libs(dir));
    cc(&exe, &link);
    exe
}

/// What a static library of this toolchain must be linked with, from
/// rustc itself: `-lgcc_s -lutil -lrt -lpthread -lm -ldl -lc` on Linux,
/// the standard library's needs (this crate's dependencies add only libc
/// and libm, which the list holds: docs/shading-c-api.md).
fn native_static_libs(dir: &Path) -> Vec<String> {
    let src = dir.join("empty.rs");
    std::fs::write(&src, "").unwrap();
    let rustc = std::env::var_os("RUSTC").unwrap_or_else(|| "rustc".into());
    let out = Command::new(&rustc)
        .args(["--crate-type", "staticlib", "--print", "native-static-libs", "-o"])
        .arg(dir.join("libempty.a"))
        .arg(&src)
        .output()
        .unwrap_or_else(|e| panic!("{rustc:?}: {e}"));
    let note = String::from_utf8_lossy(&out.stderr);
    let libs = note
        .lines()
        .find_map(|l| l.split_once("native-static-libs: "))
        .unwrap_or_else(|| panic!("rustc printed no native-static-libs: {note}"))
        .1;
    libs.split_whitespace().map(String::from).collect()
}

/// The system's C compiler (`$CC`, else `cc`: the one Rust links with)
/// on `examples/shade.c`, warnings as errors, with `link` after it.
fn cc(exe: &Path, link: &[String]) {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let cc = std::env::var_os("CC").unwrap_or_else(|| "cc".into());
    let out = Command::new(&cc)
        .args(["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"])
        .arg(manifest.join("examples/shade.c"))
        .arg("-I")
        .arg(manifest.join("include"))
        .args(link)
        .arg("-o")
        .arg(exe)
        .output()
        .unwrap_or_else(|e| panic!("{cc:?} (the C compiler Rust links with): {e}"));
    assert!(out.status.success(), "{cc:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// Run the compiled program on `material` with `queries` on its input:
/// (exit code, standard output, standard error).
fn run(
    exe: &Path,
    material: &Path,
    from_memory: bool,
    queries: &[ShadeQuery],
) -> (i32, String, String) {
    use std::io::Write;
    let mut cmd = Command::new(exe);
    cmd.arg(material);
    if from_memory {
        cmd.arg("--from-memory");
    }
    let mut child = cmd
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut text = String::new();
    for q in queries {
        // Rust's shortest round-trip form: C's strtof reads the same float
        // back (NaN as "NaN").
        let v: Vec<String> =
            q.uv.iter().chain(&q.wi).chain(&q.wo).map(|x| format!("{x:?}")).collect();
        text.push_str(&v.join(" "));
        text.push('\n');
    }
    child.stdin.take().unwrap().write_all(text.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8(out.stdout).unwrap(),
        String::from_utf8(out.stderr).unwrap(),
    )
}

#[test]
fn a_c_program_shades_every_kind_of_file_as_the_rust_api_does() {
    let dir = tempfile::tempdir().unwrap();
    shades_as_rust_does(&compile(dir.path()), dir.path());
}

#[test]
fn linked_statically_it_shades_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let exe = compile_static(dir.path());
    // Nothing of the shared library: the C runtime's libraries only.
    #[cfg(target_os = "linux")]
    {
        let ldd = Command::new("ldd").arg(&exe).output().expect("ldd (glibc's libc-bin)");
        let deps = String::from_utf8_lossy(&ldd.stdout);
        assert!(ldd.status.success() && deps.contains("libc.so"), "ldd: {deps}");
        assert!(!deps.contains("scanner_shading_c"), "{deps}");
    }
    shades_as_rust_does(&exe, dir.path());
}

/// The program `exe` answers every query on every kind of file exactly as
/// `Material::eval` does, from the file and from memory.
fn shades_as_rust_does(exe: &Path, dir: &Path) {
    for (name, data) in materials() {
        let path = dir.join(format!("{name}.material"));
        std::fs::write(&path, data.to_bytes().unwrap()).unwrap();
        let m = Material::open(&path).unwrap();
        let q = queries(&m);
        for from_memory in [false, true] {
            let (code, stdout, stderr) = run(exe, &path, from_memory, &q);
            assert_eq!(code, 0, "{name}: {stderr}");
            let mut lines = stdout.lines();
            let e = m.metadata().extent_mm;
            let json = serde_json::to_string(m.metadata()).unwrap();
            // "extent U V metadata N bytes", U and V to 17 digits: exact.
            let head: Vec<&str> = lines.next().unwrap().split(' ').collect();
            let extent = [head[1], head[2]].map(|x| x.parse::<f64>().unwrap());
            assert_eq!(extent, e, "{name}: {head:?}");
            assert_eq!(head[4].parse::<usize>().unwrap(), json.len(), "{name}: {head:?}");
            let answers: Vec<Vec<f32>> =
                lines.map(|l| l.split(' ').map(|x| x.parse::<f32>().unwrap()).collect()).collect();
            assert_eq!(answers.len(), q.len(), "{name}: one line per query");
            let (mut lit, mut drawn_count) = (0, 0);
            for (k, (a, q)) in answers.iter().zip(&q).enumerate() {
                let want = m.eval(q.uv, q.wi, q.wo);
                let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&a[..3]), bits(&want), "{name}: query {k} {q:?}, eval");
                assert_eq!(bits(&a[3..6]), bits(&want), "{name}: query {k} {q:?}, batch");
                let pdf = m.pdf(q.uv, q.wi, q.wo);
                assert_eq!(a[6].to_bits(), pdf.to_bits(), "{name}: query {k} {q:?}, pdf");
                let drawn = m.sample(q.uv, q.wo, q.uv[0], [q.uv[1], 0.5]);
                assert_eq!(a[7] == 1.0, drawn.is_some(), "{name}: query {k} {q:?}, sample");
                if let Some(s) = drawn {
                    let c = [s.wi, s.f_cos].concat();
                    assert_eq!(bits(&a[8..14]), bits(&c), "{name}: query {k} {q:?}, sample");
                    assert_eq!(a[14].to_bits(), s.pdf.to_bits(), "{name}: query {k} {q:?}");
                    drawn_count += 1;
                }
                lit += usize::from(want.iter().any(|&x| x > 0.0));
            }
            // Not a test of black answers only: all but the five special
            // queries' four black ones are lit.
            assert!(lit >= q.len() - 4, "{name}: {lit} of {} lit", q.len());
            assert!(drawn_count > q.len() / 2, "{name}: {drawn_count} of {} drawn", q.len());
        }
    }
}

#[test]
fn bad_files_give_a_status_and_a_message_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let exe = compile(dir.path());
    let good = materials().remove(0).1.to_bytes().unwrap();
    let truncated = dir.path().join("truncated.material");
    std::fs::write(&truncated, &good[..good.len() / 2]).unwrap();
    let missing = dir.path().join("missing.material");
    let cases: [(&Path, bool, &str); 5] = [
        (&missing, false, "error 1: "),
        (&truncated, false, "error 2: "),
        // A directory is no material file.
        (dir.path(), false, "error 2: "),
        // From memory there is no file to name: the reason alone.
        (&truncated, true, "error 2: "),
        (Path::new("/dev/null"), false, "error 2: "),
    ];
    for (path, from_memory, status) in cases {
        let (code, stdout, stderr) = run(&exe, path, from_memory, &[]);
        assert_eq!(code, 3, "{}: {stdout}", path.display());
        assert!(stderr.starts_with(status), "{}: {stderr}", path.display());
        if !from_memory {
            assert!(stderr.contains(&path.display().to_string()), "names the file: {stderr}");
        }
        assert!(stdout.is_empty());
    }
}

/// A material opened through the C API from its bytes.
fn open_bytes(bytes: &[u8]) -> *mut ScannerMaterial {
    let mut m = std::ptr::null_mut();
    let status = unsafe {
        scanner_material_open_bytes(bytes.as_ptr(), bytes.len(), &mut m, std::ptr::null_mut(), 0)
    };
    assert_eq!(status, SCANNER_OK);
    m
}

#[test]
fn null_pointers_and_short_buffers_are_refused_or_cut_safely() {
    let bytes = materials().remove(2).1.to_bytes().unwrap();
    let mut err = [0 as c_char; 64];
    let mut m = std::ptr::null_mut();
    let message =
        |err: &[c_char]| unsafe { CStr::from_ptr(err.as_ptr()) }.to_str().unwrap().to_string();
    unsafe {
        assert_eq!(scanner_shading_abi_version(), ABI_VERSION);
        let path = CString::new("x.material").unwrap();
        let s = scanner_material_open(path.as_ptr(), std::ptr::null_mut(), err.as_mut_ptr(), 64);
        assert_eq!(s, SCANNER_ERROR_ARGUMENT);
        assert!(message(&err).contains("null pointer"));
        let s = scanner_material_open(std::ptr::null(), &mut m, err.as_mut_ptr(), 64);
        assert_eq!(s, SCANNER_ERROR_ARGUMENT);
        let s = scanner_material_open_bytes(std::ptr::null(), 10, &mut m, err.as_mut_ptr(), 64);
        assert_eq!(s, SCANNER_ERROR_ARGUMENT);
        // Empty bytes: not a material (and no null-pointer complaint).
        let s = scanner_material_open_bytes(std::ptr::null(), 0, &mut m, err.as_mut_ptr(), 64);
        assert_eq!(s, SCANNER_ERROR_INVALID, "{}", message(&err));
        assert!(m.is_null(), "*out untouched on failure");
        // A message longer than the buffer: cut, terminated.
        let mut tiny = [0x55 as c_char; 6];
        let s = scanner_material_open_bytes(bytes.as_ptr(), 100, &mut m, tiny.as_mut_ptr(), 6);
        assert_eq!(s, SCANNER_ERROR_INVALID);
        assert_eq!(message(&tiny).len(), 5);

        // A null handle: black, zeros, nothing written.
        let q = ShadeQuery { uv: [0.5; 2], wi: [0.0, 0.0, 1.0], wo: [0.0, 0.0, 1.0] };
        assert_eq!(scanner_material_eval(std::ptr::null(), q).rgb, [0.0; 3]);
        let mut out = [ScannerRgb { rgb: [7.0; 3] }];
        assert_eq!(
            scanner_material_eval_batch(std::ptr::null(), &q, 1, out.as_mut_ptr()),
            SCANNER_ERROR_ARGUMENT
        );
        assert_eq!(out[0].rgb, [7.0; 3]);
        let mut extent = [9.0f64; 2];
        scanner_material_extent_mm(std::ptr::null(), extent.as_mut_ptr());
        assert_eq!(extent, [0.0; 2]);
        assert_eq!(scanner_material_metadata_json(std::ptr::null(), std::ptr::null_mut(), 0), 0);
        scanner_material_free(std::ptr::null_mut());
        let (up, half) = ([0.0f32, 0.0, 1.0], [0.5f32; 2]);
        let mut drawn = ScannerBsdfSample { pdf: 7.0, ..Default::default() };
        let null_handle = scanner_material_sample(
            std::ptr::null(),
            half.as_ptr(),
            up.as_ptr(),
            0.5,
            half.as_ptr(),
            &mut drawn,
        );
        assert_eq!((null_handle, drawn.pdf), (0, 7.0));
        assert_eq!(
            scanner_material_pdf(std::ptr::null(), half.as_ptr(), up.as_ptr(), up.as_ptr()),
            0.0
        );
        scanner_material_prepare_importance(std::ptr::null());

        let m = open_bytes(&bytes);
        // Null arrays or output: no draw, nothing written.
        let (uv, wo, u) = (half.as_ptr(), up.as_ptr(), half.as_ptr());
        let null = std::ptr::null::<f32>();
        for (uv, wo, u) in [(null, wo, u), (uv, null, u), (uv, wo, null)] {
            assert_eq!(scanner_material_sample(m, uv, wo, 0.5, u, &mut drawn), 0);
        }
        assert_eq!(drawn.pdf, 7.0);
        assert_eq!(scanner_material_sample(m, uv, wo, 0.5, u, std::ptr::null_mut()), 0);
        assert_eq!(scanner_material_pdf(m, uv, null, wo), 0.0);
        assert_eq!(scanner_material_pdf(m, uv, wo, null), 0.0);
        assert_eq!(scanner_material_pdf(m, null, wo, wo), 0.0);
        assert_eq!(scanner_material_sample(m, uv, wo, 0.5, u, &mut drawn), 1);
        assert!(drawn.pdf > 0.0 && drawn.pdf == scanner_material_pdf(m, uv, drawn.wi.as_ptr(), wo));
        assert_eq!(
            scanner_material_eval_batch(m, std::ptr::null(), 0, std::ptr::null_mut()),
            SCANNER_OK
        );
        assert_eq!(
            scanner_material_eval_batch(m, &q, 1, std::ptr::null_mut()),
            SCANNER_ERROR_ARGUMENT
        );
        // Metadata: its length with no buffer, cut to fit a short one.
        let full = scanner_material_metadata_json(m, std::ptr::null_mut(), 0);
        let mut buf = vec![0 as c_char; full + 1];
        assert_eq!(scanner_material_metadata_json(m, buf.as_mut_ptr(), buf.len()), full);
        let text = message(&buf);
        assert_eq!(text.len(), full);
        let meta: scanner_shading::Metadata = serde_json::from_str(&text).unwrap();
        assert_eq!(meta, *Material::from_bytes(&bytes).unwrap().metadata());
        assert_eq!(scanner_material_metadata_json(m, buf.as_mut_ptr(), 10), full);
        assert_eq!(message(&buf), text[..9]);
        scanner_material_free(m);
    }
}

#[test]
fn threads_share_one_handle() {
    let bytes = materials().remove(2).1.to_bytes().unwrap();
    let rust = Material::from_bytes(&bytes).unwrap();
    let q = queries(&rust);
    let want: Vec<[f32; 3]> = q.iter().map(|q| rust.eval(q.uv, q.wi, q.wo)).collect();
    let pdfs: Vec<f32> = q.iter().map(|q| rust.pdf(q.uv, q.wi, q.wo)).collect();
    let m = open_bytes(&bytes);
    // Raw pointers are not Send: the handle crosses as an address.
    let handle = m as usize;
    std::thread::scope(|s| {
        for t in 0..4 {
            let (q, want, pdfs) = (&q, &want, &pdfs);
            s.spawn(move || {
                let m = handle as *const ScannerMaterial;
                for round in 0..20 {
                    let mut out = vec![ScannerRgb::default(); q.len()];
                    let status = unsafe {
                        scanner_material_eval_batch(m, q.as_ptr(), q.len(), out.as_mut_ptr())
                    };
                    assert_eq!(status, SCANNER_OK);
                    for (k, (o, w)) in out.iter().zip(want).enumerate() {
                        assert_eq!(
                            o.rgb.map(f32::to_bits),
                            w.map(f32::to_bits),
                            "thread {t} round {round} query {k}"
                        );
                        let one = unsafe { scanner_material_eval(m, q[k]) };
                        assert_eq!(one.rgb.map(f32::to_bits), w.map(f32::to_bits));
                        // The sampling tables, built on first use by
                        // whichever thread comes first.
                        let pdf = unsafe {
                            scanner_material_pdf(
                                m,
                                q[k].uv.as_ptr(),
                                q[k].wi.as_ptr(),
                                q[k].wo.as_ptr(),
                            )
                        };
                        assert_eq!(pdf.to_bits(), pdfs[k].to_bits(), "thread {t} query {k}");
                    }
                }
            });
        }
    });
    unsafe { scanner_material_free(m) };
}
