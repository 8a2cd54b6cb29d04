//! # scanner-shading-c
//!
//! The shading API of [`scanner_shading`] for renderers written in C or
//! C++: `libscanner_shading_c.so` (`.dylib`, `.dll`) and its header
//! `include/scanner_shading.h`. Every function is a thin wrapper: one copy
//! of the reader and of the shading, the Rust crate's.
//!
//! - A material is opened from a file or from bytes in memory into an
//!   opaque handle, which every other call takes; errors are a status code
//!   and a message in a caller's buffer, never a crash.
//! - `scanner_material_eval` answers one query by value,
//!   `scanner_material_eval_batch` many (the faster form: docs/benchmarks.md,
//!   "Shading speed"). Neither allocates. The answer is f · cos θi, linear
//!   RGB, in the sample's frame (docs/material-format.md, "Shading").
//! - `scanner_material_sample` draws a light direction with a density close
//!   to f · cos θi, `scanner_material_pdf` gives that density (for multiple
//!   importance sampling); `scanner_material_prepare_importance` builds
//!   their tables up front, after which neither allocates.
//! - A handle is immutable once opened: any number of threads may shade
//!   with one handle at once; only `scanner_material_free` must come after
//!   every other call on it.
//! - No panic unwinds into C: a Rust panic (none is known; the reader is
//!   fuzzed) becomes [`SCANNER_ERROR_INTERNAL`] or a black answer.
//!
//! docs/shading-c-api.md documents the API for C users; the header is the
//! reference, and `tests/c_api.rs` compiles `examples/shade.c` against it
//! and checks every answer against [`Material::eval`].

use std::ffi::{CStr, c_char, c_int};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;

use scanner_shading::{Material, MaterialError, ShadeQuery};

/// The header's `SCANNER_SHADING_ABI_VERSION`: a program built against
/// another header must not use this library.
pub const ABI_VERSION: u32 = 1;

/// Success.
pub const SCANNER_OK: c_int = 0;
/// The file cannot be read (missing, no permission).
pub const SCANNER_ERROR_IO: c_int = 1;
/// Not a valid material: not a regular file, damaged, truncated, or values
/// out of range.
pub const SCANNER_ERROR_INVALID: c_int = 2;
/// A null pointer where one is required, or a path that is not one.
pub const SCANNER_ERROR_ARGUMENT: c_int = 3;
/// A fault of this library (a panic caught at the boundary).
pub const SCANNER_ERROR_INTERNAL: c_int = 4;

/// An opened material: the header's opaque `ScannerMaterial`.
#[derive(Debug)]
pub struct ScannerMaterial(Material);

/// One answer: f · cos θi, linear RGB (the header's `ScannerRgb`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ScannerRgb {
    /// Red, green, blue.
    pub rgb: [f32; 3],
}

// The header's layouts: `ScannerShadeQuery` is `ShadeQuery` (uv, wi, wo as
// 8 floats), `ScannerRgb` is three floats, so the batch reads and writes
// the caller's arrays in place.
const _: () = assert!(size_of::<ShadeQuery>() == 32 && align_of::<ShadeQuery>() == 4);
const _: () = assert!(size_of::<ScannerRgb>() == 12 && align_of::<ScannerRgb>() == 4);
const _: () = assert!(std::mem::offset_of!(ShadeQuery, wi) == 8);
const _: () = assert!(std::mem::offset_of!(ShadeQuery, wo) == 20);

/// The ABI version this library implements ([`ABI_VERSION`]).
#[unsafe(no_mangle)]
pub extern "C" fn scanner_shading_abi_version() -> u32 {
    ABI_VERSION
}

/// Write `message` into the caller's buffer `error` of `len` bytes,
/// truncated at a character boundary and NUL-terminated (nothing if
/// `error` is null or `len` is 0).
///
/// # Safety
/// `error`, if not null, must be valid for writes of `len` bytes.
unsafe fn write_message(message: &str, error: *mut c_char, len: usize) {
    if error.is_null() || len == 0 {
        return;
    }
    let mut n = message.len().min(len - 1);
    while !message.is_char_boundary(n) {
        n -= 1;
    }
    // SAFETY: the caller gives `len` writable bytes; n + 1 ≤ len.
    unsafe {
        std::ptr::copy_nonoverlapping(message.as_ptr().cast::<c_char>(), error, n);
        *error.add(n) = 0;
    }
}

/// The status of a reader's error.
fn status(e: &MaterialError) -> c_int {
    match e {
        MaterialError::Io { .. } => SCANNER_ERROR_IO,
        _ => SCANNER_ERROR_INVALID,
    }
}

/// Run `open`, store its material in `*out` or report its error: the
/// status code, the message in `error`.
///
/// # Safety
/// `out` must be valid for a write; `error` as [`write_message`] says.
unsafe fn finish_open(
    open: impl FnOnce() -> Result<Material, (c_int, String)>,
    out: *mut *mut ScannerMaterial,
    error: *mut c_char,
    error_len: usize,
) -> c_int {
    let result = catch_unwind(AssertUnwindSafe(open)).unwrap_or_else(|panic| {
        let what = panic
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| panic.downcast_ref::<String>().cloned())
            .unwrap_or_default();
        Err((SCANNER_ERROR_INTERNAL, format!("internal error of scanner-shading: {what}")))
    });
    match result {
        Ok(m) => {
            // SAFETY: the caller gives a writable `out`.
            unsafe { *out = Box::into_raw(Box::new(ScannerMaterial(m))) };
            SCANNER_OK
        }
        Err((code, message)) => {
            // SAFETY: as the caller's contract says.
            unsafe { write_message(&message, error, error_len) };
            code
        }
    }
}

/// Open and check the material file at `path` (a NUL-terminated path; on
/// Unix any bytes, elsewhere UTF-8). On success stores a handle in `*out`
/// and returns [`SCANNER_OK`]; otherwise leaves `*out` unchanged, returns
/// an error status and writes a message naming the file into `error` (up
/// to `error_len` bytes with the NUL; `error` may be null).
///
/// # Safety
/// `path` null or NUL-terminated; `out` null or writable; `error` null or
/// writable for `error_len` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_open(
    path: *const c_char,
    out: *mut *mut ScannerMaterial,
    error: *mut c_char,
    error_len: usize,
) -> c_int {
    if out.is_null() || path.is_null() {
        // SAFETY: as the caller's contract says.
        unsafe { write_message("scanner_material_open: a null pointer", error, error_len) };
        return SCANNER_ERROR_ARGUMENT;
    }
    // SAFETY: a NUL-terminated string, as the caller's contract says.
    let bytes = unsafe { CStr::from_ptr(path) }.to_bytes();
    #[cfg(unix)]
    let path: Result<PathBuf, ()> = {
        use std::os::unix::ffi::OsStrExt;
        Ok(PathBuf::from(std::ffi::OsStr::from_bytes(bytes)))
    };
    #[cfg(not(unix))]
    let path = std::str::from_utf8(bytes).map(PathBuf::from);
    let Ok(path) = path else {
        // SAFETY: as the caller's contract says.
        unsafe { write_message("scanner_material_open: the path is not UTF-8", error, error_len) };
        return SCANNER_ERROR_ARGUMENT;
    };
    let open = || Material::open(&path).map_err(|e| (status(&e), e.to_string()));
    // SAFETY: as the caller's contract says.
    unsafe { finish_open(open, out, error, error_len) }
}

/// Open a material from a file's `len` bytes in memory (copied: the
/// caller may free them after the call). Status, `*out` and `error` as for
/// [`scanner_material_open`].
///
/// # Safety
/// `bytes` readable for `len` bytes (or null with `len` 0); `out` and
/// `error` as for [`scanner_material_open`].
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_open_bytes(
    bytes: *const u8,
    len: usize,
    out: *mut *mut ScannerMaterial,
    error: *mut c_char,
    error_len: usize,
) -> c_int {
    if out.is_null() || (bytes.is_null() && len > 0) {
        // SAFETY: as the caller's contract says.
        unsafe { write_message("scanner_material_open_bytes: a null pointer", error, error_len) };
        return SCANNER_ERROR_ARGUMENT;
    }
    let data: &[u8] = if len == 0 {
        &[]
    } else {
        // SAFETY: readable for `len` bytes, as the caller's contract says.
        unsafe { std::slice::from_raw_parts(bytes, len) }
    };
    let open = || Material::from_bytes(data).map_err(|e| (status(&e), e.to_string()));
    // SAFETY: as the caller's contract says.
    unsafe { finish_open(open, out, error, error_len) }
}

/// Free a handle (null: nothing). No other call on it may follow or run
/// at the same time.
///
/// # Safety
/// `m` null or a handle from `scanner_material_open*` not yet freed.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_free(m: *mut ScannerMaterial) {
    if !m.is_null() {
        // SAFETY: a handle made by `Box::into_raw`, freed once.
        drop(unsafe { Box::from_raw(m) });
    }
}

/// f(uv, wi, wo) · cos θi of one query, linear RGB ([`Material::eval`]);
/// black for a null handle.
///
/// # Safety
/// `m` null or a live handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_eval(
    m: *const ScannerMaterial,
    query: ShadeQuery,
) -> ScannerRgb {
    // SAFETY: null or a live handle, as the caller's contract says.
    let Some(m) = (unsafe { m.as_ref() }) else {
        return ScannerRgb::default();
    };
    let eval = || m.0.eval(query.uv, query.wi, query.wo);
    ScannerRgb { rgb: catch_unwind(AssertUnwindSafe(eval)).unwrap_or_default() }
}

/// Answer `count` queries into `out[0..count]` ([`Material::eval_batch`]:
/// the same answers as one at a time, faster). Returns [`SCANNER_OK`], or
/// [`SCANNER_ERROR_ARGUMENT`] for a null pointer with `count` > 0 (nothing
/// written), or [`SCANNER_ERROR_INTERNAL`] (every answer black).
///
/// # Safety
/// `m` null or a live handle; `queries` readable and `out` writable for
/// `count` elements, not overlapping.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_eval_batch(
    m: *const ScannerMaterial,
    queries: *const ShadeQuery,
    count: usize,
    out: *mut ScannerRgb,
) -> c_int {
    if count == 0 {
        return SCANNER_OK;
    }
    // SAFETY: null or a live handle, as the caller's contract says.
    let Some(m) = (unsafe { m.as_ref() }) else {
        return SCANNER_ERROR_ARGUMENT;
    };
    if queries.is_null() || out.is_null() {
        return SCANNER_ERROR_ARGUMENT;
    }
    // SAFETY: `count` readable queries and writable answers, as the
    // caller's contract says; `ScannerRgb` is laid out as `[f32; 3]`.
    let (q, o) = unsafe {
        (
            std::slice::from_raw_parts(queries, count),
            std::slice::from_raw_parts_mut(out.cast::<[f32; 3]>(), count),
        )
    };
    match catch_unwind(AssertUnwindSafe(|| m.0.eval_batch(q, o))) {
        Ok(()) => SCANNER_OK,
        Err(_) => {
            o.fill([0.0; 3]);
            SCANNER_ERROR_INTERNAL
        }
    }
}

/// A drawn direction (the header's `ScannerBsdfSample`,
/// [`scanner_shading::BsdfSample`]).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ScannerBsdfSample {
    /// Towards the light, unit, above the horizon.
    pub wi: [f32; 3],
    /// f · cos θi at (uv, wi, wo), as `scanner_material_eval` answers.
    pub f_cos: [f32; 3],
    /// wi's density per unit solid angle, as `scanner_material_pdf` answers.
    pub pdf: f32,
}

const _: () = assert!(size_of::<ScannerBsdfSample>() == 28);

/// `n` floats at `p`, or `None` for a null pointer.
///
/// # Safety
/// `p` null or readable for `n` floats.
unsafe fn floats<const N: usize>(p: *const f32) -> Option<[f32; N]> {
    // SAFETY: null or readable for N floats, as the caller's contract says.
    (!p.is_null()).then(|| unsafe { std::ptr::read_unaligned(p.cast::<[f32; N]>()) })
}

/// Draw a direction towards the light for the view `wo` at `uv` from
/// uniform numbers `uc` and `u` ([`Material::sample`]). Returns 1 with the
/// draw in `*out`, or 0 (nothing written) if there is none: wo not a
/// direction above the horizon, uv not finite, a draw below the horizon,
/// a null pointer or a fault.
///
/// # Safety
/// `m` null or a live handle; `uv` and `u` null or readable for 2 floats,
/// `wo` for 3; `out` null or writable.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_sample(
    m: *const ScannerMaterial,
    uv: *const f32,
    wo: *const f32,
    uc: f32,
    u: *const f32,
    out: *mut ScannerBsdfSample,
) -> c_int {
    // SAFETY: each pointer null or valid as the caller's contract says.
    let (Some(m), Some(uv), Some(wo), Some(u)) =
        (unsafe { (m.as_ref(), floats::<2>(uv), floats::<3>(wo), floats::<2>(u)) })
    else {
        return 0;
    };
    if out.is_null() {
        return 0;
    }
    match catch_unwind(AssertUnwindSafe(|| m.0.sample(uv, wo, uc, u))) {
        Ok(Some(s)) => {
            // SAFETY: non-null and writable, as the caller's contract says.
            unsafe { out.write(ScannerBsdfSample { wi: s.wi, f_cos: s.f_cos, pdf: s.pdf }) };
            1
        }
        _ => 0,
    }
}

/// The density per unit solid angle with which `scanner_material_sample`
/// draws `wi` for the view `wo` at `uv` ([`Material::pdf`]); 0 for a null
/// pointer, uv not finite or a direction not above the horizon.
///
/// # Safety
/// `m` null or a live handle; `uv` null or readable for 2 floats, `wi` and
/// `wo` for 3.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_pdf(
    m: *const ScannerMaterial,
    uv: *const f32,
    wi: *const f32,
    wo: *const f32,
) -> f32 {
    // SAFETY: each pointer null or valid as the caller's contract says.
    let (Some(m), Some(uv), Some(wi), Some(wo)) =
        (unsafe { (m.as_ref(), floats::<2>(uv), floats::<3>(wi), floats::<3>(wo)) })
    else {
        return 0.0;
    };
    catch_unwind(AssertUnwindSafe(|| m.0.pdf(uv, wi, wo))).unwrap_or(0.0)
}

/// Build the sampling tables of every view now, on all cores
/// ([`Material::prepare_importance`]); otherwise each is built on its
/// first use. Nothing for a null handle.
///
/// # Safety
/// `m` null or a live handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_prepare_importance(m: *const ScannerMaterial) {
    // SAFETY: null or a live handle, as the caller's contract says.
    if let Some(m) = unsafe { m.as_ref() } {
        let _ = catch_unwind(AssertUnwindSafe(|| m.0.prepare_importance()));
    }
}

/// The size of what uv ∈ [0, 1]² spans, mm (u, v); zeros for a null
/// handle.
///
/// # Safety
/// `m` null or a live handle; `out` null or writable for 2 doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_extent_mm(m: *const ScannerMaterial, out: *mut f64) {
    if out.is_null() {
        return;
    }
    // SAFETY: null or a live handle, as the caller's contract says.
    let e = unsafe { m.as_ref() }.map_or([0.0; 2], |m| m.0.metadata().extent_mm);
    // SAFETY: writable for 2 doubles, as the caller's contract says.
    unsafe { std::ptr::copy_nonoverlapping(e.as_ptr(), out, 2) };
}

/// The file's JSON metadata (docs/material-format.md, "Metadata") as
/// NUL-terminated UTF-8 in `buf` (up to `len` bytes with the NUL, cut at
/// a character boundary; `buf` may be null). Returns the whole text's
/// length without the NUL, as `snprintf` does: call with `len` 0 to size
/// the buffer. 0 for a null handle.
///
/// # Safety
/// `m` null or a live handle; `buf` null or writable for `len` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn scanner_material_metadata_json(
    m: *const ScannerMaterial,
    buf: *mut c_char,
    len: usize,
) -> usize {
    // SAFETY: null or a live handle, as the caller's contract says.
    let Some(m) = (unsafe { m.as_ref() }) else {
        // SAFETY: as the caller's contract says.
        unsafe { write_message("", buf, len) };
        return 0;
    };
    // Serialising a checked metadata document cannot fail (strings,
    // finite numbers and lists only).
    let text = serde_json::to_string(m.0.metadata()).unwrap_or_default();
    // SAFETY: as the caller's contract says.
    unsafe { write_message(&text, buf, len) };
    text.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_are_cut_at_a_character_boundary_and_terminated() {
        let mut buf = [0x55 as c_char; 8];
        // "é" is two bytes: 7 bytes of room keep "abcdé" whole? a, b, c, d,
        // é (2) = 6 bytes, then "f" — 7; the NUL is the 8th.
        unsafe { write_message("abcdéfgh", buf.as_mut_ptr(), buf.len()) };
        let s = unsafe { CStr::from_ptr(buf.as_ptr()) }.to_str().unwrap();
        assert_eq!(s, "abcdéf");
        // Room for 5 bytes: "é" would be cut in half, so it is left out.
        let mut small = [0x55 as c_char; 6];
        unsafe { write_message("abcdé", small.as_mut_ptr(), small.len()) };
        assert_eq!(unsafe { CStr::from_ptr(small.as_ptr()) }.to_str().unwrap(), "abcd");
        // No room at all, or no buffer: nothing written, no crash.
        unsafe { write_message("abc", small.as_mut_ptr(), 0) };
        assert_eq!(small[0], b'a' as c_char);
        unsafe { write_message("abc", std::ptr::null_mut(), 10) };
    }
}
