/*
 * shade.c — the C API in use: open a material, answer queries read from
 * standard input, print the answers.
 *
 *   cc -std=c99 shade.c -I host/shading-c/include -L target/release \
 *      -lscanner_shading_c -Wl,-rpath,target/release -o shade
 *   ./shade woven-fabric.material [--from-memory] < queries.txt
 *
 * Each input line is one query, 8 numbers: u v wi_x wi_y wi_z wo_x wo_y wo_z.
 * The first output line gives the material's extent and metadata size;
 * then one line per query: the answer of scanner_material_eval, then that
 * of scanner_material_eval_batch (the same numbers), scanner_material_pdf
 * of its uv, wi and wo, then 1 and a draw of scanner_material_sample for its
 * uv and wo (uc = u, u = (v, 0.5)): wi, f_cos, pdf; or 0 and zeros. Exit status 3 if the
 * material cannot be opened, with the library's message.
 * host/shading-c/tests/c_api.rs runs it.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "scanner_shading.h"

/* The whole file in memory, or NULL. */
static uint8_t *read_file(const char *path, size_t *len) {
    FILE *f = fopen(path, "rb");
    if (!f) return NULL;
    uint8_t *buf = NULL;
    size_t cap = 0, n = 0, got;
    do {
        if (n == cap) {
            cap = cap ? 2 * cap : 1 << 16;
            uint8_t *grown = realloc(buf, cap);
            if (!grown) {
                free(buf);
                fclose(f);
                return NULL;
            }
            buf = grown;
        }
        got = fread(buf + n, 1, cap - n, f);
        n += got;
    } while (got > 0);
    fclose(f);
    *len = n;
    return buf;
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s MATERIAL [--from-memory] < queries\n", argv[0]);
        return 2;
    }
    if (scanner_shading_abi_version() != SCANNER_SHADING_ABI_VERSION) {
        fprintf(stderr, "libscanner_shading_c has ABI %u, this program %u\n",
                scanner_shading_abi_version(), SCANNER_SHADING_ABI_VERSION);
        return 2;
    }
    char error[512];
    ScannerMaterial *m = NULL;
    int status;
    if (argc > 2 && strcmp(argv[2], "--from-memory") == 0) {
        size_t len = 0;
        uint8_t *bytes = read_file(argv[1], &len);
        if (!bytes) {
            fprintf(stderr, "%s: cannot read\n", argv[1]);
            return 3;
        }
        status = scanner_material_open_bytes(bytes, len, &m, error, sizeof error);
        free(bytes);
    } else {
        status = scanner_material_open(argv[1], &m, error, sizeof error);
    }
    if (status != SCANNER_OK) {
        fprintf(stderr, "error %d: %s\n", status, error);
        return 3;
    }

    double extent[2];
    scanner_material_extent_mm(m, extent);
    size_t meta_len = scanner_material_metadata_json(m, NULL, 0);
    char *meta = malloc(meta_len + 1);
    if (!meta || scanner_material_metadata_json(m, meta, meta_len + 1) != meta_len ||
        strlen(meta) != meta_len) {
        fprintf(stderr, "metadata\n");
        return 1;
    }
    printf("extent %.17g %.17g metadata %zu bytes\n", extent[0], extent[1], meta_len);
    free(meta);

    size_t count = 0, cap = 0;
    ScannerShadeQuery *queries = NULL;
    ScannerShadeQuery q;
    while (scanf("%f %f %f %f %f %f %f %f", &q.uv[0], &q.uv[1], &q.wi[0], &q.wi[1], &q.wi[2],
                 &q.wo[0], &q.wo[1], &q.wo[2]) == 8) {
        if (count == cap) {
            cap = cap ? 2 * cap : 256;
            ScannerShadeQuery *grown = realloc(queries, cap * sizeof *queries);
            if (!grown) return 1;
            queries = grown;
        }
        queries[count++] = q;
    }
    ScannerRgb *batch = malloc((count ? count : 1) * sizeof *batch);
    if (!batch || scanner_material_eval_batch(m, queries, count, batch) != SCANNER_OK) {
        fprintf(stderr, "batch\n");
        return 1;
    }
    scanner_material_prepare_importance(m);
    for (size_t i = 0; i < count; i++) {
        ScannerRgb one = scanner_material_eval(m, queries[i]);
        /* A draw for the query's view with uc = u and u = (v, 0.5). */
        const ScannerShadeQuery *qi = &queries[i];
        float u[2] = {qi->uv[1], 0.5f};
        ScannerBsdfSample s = {{0, 0, 0}, {0, 0, 0}, 0};
        int drawn = scanner_material_sample(m, qi->uv, qi->wo, qi->uv[0], u, &s);
        /* %.9g: every float printed exactly (9 significant digits). */
        printf("%.9g %.9g %.9g %.9g %.9g %.9g %.9g %d %.9g %.9g %.9g %.9g %.9g %.9g %.9g\n",
               one.rgb[0], one.rgb[1], one.rgb[2], batch[i].rgb[0], batch[i].rgb[1],
               batch[i].rgb[2], scanner_material_pdf(m, qi->uv, qi->wi, qi->wo), drawn, s.wi[0],
               s.wi[1], s.wi[2], s.f_cos[0], s.f_cos[1], s.f_cos[2], s.pdf);
    }
    free(batch);
    free(queries);
    scanner_material_free(m);
    return 0;
}
