/*
 * scanner_shading.h — shade scanned materials (.material files) from C or
 * C++. Link with libscanner_shading_c (cargo build --release -p
 * scanner-shading-c: target/release/libscanner_shading_c.so, .dylib or
 * .dll). docs/shading-c-api.md has the guide; docs/material-format.md the
 * file and what an answer means.
 *
 * Frame: directions are in the sample's frame — z along its normal, x
 * along +u, y along +v — and point away from the surface: wi towards the
 * light, wo towards the viewer. They are normalised here; one shorter than
 * 1e-6 or not finite gives black, and so does one below the horizon
 * (z <= 0). uv in [0, 1]^2 spans the material's extent
 * (scanner_material_extent_mm) and wraps outside it.
 *
 * Answer: f(uv, wi, wo) * cos(theta_i), linear RGB: the radiance towards
 * wo per unit irradiance arriving along wi at normal incidence. Like
 * Mitsuba's BSDF::eval, unlike pbrt's f(), which excludes the cosine.
 *
 * Threads: a handle is immutable once opened (sampling tables are built
 * once, safely). Any number of threads may call the eval, sample, pdf,
 * extent and metadata functions on one handle at once;
 * scanner_material_free must come after all of them. No call allocates
 * per query, and none unwinds or aborts on bad input.
 */
#ifndef SCANNER_SHADING_H
#define SCANNER_SHADING_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The ABI this header describes: compare with scanner_shading_abi_version(). */
#define SCANNER_SHADING_ABI_VERSION 1u

/* Status codes. */
#define SCANNER_OK 0
#define SCANNER_ERROR_IO 1       /* the file cannot be read: missing, no permission */
#define SCANNER_ERROR_INVALID 2  /* not a valid material: not a regular file, damaged, truncated, out of range */
#define SCANNER_ERROR_ARGUMENT 3 /* a null pointer where one is required; a path not UTF-8 (Windows) */
#define SCANNER_ERROR_INTERNAL 4 /* a fault of the library itself */

/* An opened material (opaque). */
typedef struct ScannerMaterial ScannerMaterial;

/* One query: 32 bytes, the layout of scanner_shading::ShadeQuery. */
typedef struct ScannerShadeQuery {
    float uv[2]; /* position over the material's extent */
    float wi[3]; /* towards the light, sample frame */
    float wo[3]; /* towards the viewer, sample frame */
} ScannerShadeQuery;

/* One answer: f * cos(theta_i), linear RGB. */
typedef struct ScannerRgb {
    float rgb[3];
} ScannerRgb;

/* The ABI version of the library loaded (SCANNER_SHADING_ABI_VERSION when
 * it matches this header). */
uint32_t scanner_shading_abi_version(void);

/* Open and check the material file at `path` (NUL-terminated; on Unix any
 * bytes, elsewhere UTF-8). On SCANNER_OK stores a handle in *out; otherwise
 * leaves *out unchanged, returns the status and writes a NUL-terminated
 * message naming the file into `error` (at most error_len bytes with the
 * NUL; error may be NULL). */
int scanner_material_open(const char *path, ScannerMaterial **out, char *error,
                          size_t error_len);

/* The same from a file's `len` bytes in memory (copied: free them when
 * this returns). */
int scanner_material_open_bytes(const uint8_t *bytes, size_t len, ScannerMaterial **out,
                                char *error, size_t error_len);

/* Free a handle (NULL: nothing). */
void scanner_material_free(ScannerMaterial *m);

/* One answer. Black for a NULL handle. */
ScannerRgb scanner_material_eval(const ScannerMaterial *m, ScannerShadeQuery query);

/* Answers to queries[0..count) into out[0..count): the same answers as one
 * at a time, faster (put queries sharing wi and wo next to each other).
 * Returns SCANNER_OK, or SCANNER_ERROR_ARGUMENT for a NULL pointer with
 * count > 0 (nothing written). The arrays must not overlap. */
int scanner_material_eval_batch(const ScannerMaterial *m, const ScannerShadeQuery *queries,
                                size_t count, ScannerRgb *out);

/* A direction drawn by scanner_material_sample: 28 bytes, the layout of
 * scanner_shading::BsdfSample. */
typedef struct ScannerBsdfSample {
    float wi[3];    /* towards the light, unit, above the horizon */
    float f_cos[3]; /* f * cos(theta_i) at (uv, wi, wo): scanner_material_eval's answer */
    float pdf;      /* density of wi per unit solid angle: scanner_material_pdf's answer, > 0 */
} ScannerBsdfSample;

/* Importance sampling: draw a direction towards the light for the view wo
 * (3 floats) at uv (2 floats) from uniform numbers uc and u[2] in [0, 1)
 * (others are clamped into it), with a density close to f * cos(theta_i).
 * Returns 1 with the draw in *out, or 0 with nothing written if there is
 * none: wo not above the horizon, uv not finite, a draw below the horizon
 * (count it as a zero sample), a NULL pointer. Throughput: f_cos / pdf.
 * The tables of wo's view are built on first use (see below). */
int scanner_material_sample(const ScannerMaterial *m, const float uv[2], const float wo[3],
                            float uc, const float u[2], ScannerBsdfSample *out);

/* The density per unit solid angle with which scanner_material_sample
 * draws wi for the view wo at uv, for multiple importance sampling; 0 if
 * either is not a direction above the horizon, uv is not finite or a
 * pointer is NULL. */
float scanner_material_pdf(const ScannerMaterial *m, const float uv[2], const float wi[3],
                           const float wo[3]);

/* Build every view's sampling table now, on all cores (well under a second
 * for a scanned material), rather than on first use: call it before
 * rendering and no sample waits or allocates. */
void scanner_material_prepare_importance(const ScannerMaterial *m);

/* The size of what uv in [0, 1]^2 spans, mm: out[0] along u, out[1] along
 * v. Zeros for a NULL handle. */
void scanner_material_extent_mm(const ScannerMaterial *m, double out[2]);

/* The file's JSON metadata, NUL-terminated, into buf (at most len bytes
 * with the NUL; buf may be NULL). Returns the whole text's length without
 * the NUL, as snprintf does: call with len 0 to size the buffer. */
size_t scanner_material_metadata_json(const ScannerMaterial *m, char *buf, size_t len);

#ifdef __cplusplus
}
#endif

#endif /* SCANNER_SHADING_H */
