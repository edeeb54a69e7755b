/*
 * memlog's compiled entropy kernel: the local Shannon entropy map of memlog/scoring/entropy.py
 * (what skimage.filters.rank.entropy(gray, disk(r)) returns), sliding one histogram along each
 * image row. Plain C, no Python API: memlog/scoring/entropy.py loads it with ctypes (which
 * releases the GIL during the call, so threads run it in parallel) and falls back to its numpy
 * implementation, with the same values, when it was not built.
 *
 * pad: the image padded by r on every side, (h + 2r) x (w + 2r) uint16, value 256 outside the
 *      image (the histogram's "outside" bin);
 * hw:  the 2r + 1 half widths of the disk's rows (dy = -r..r);
 * f:   f[k] = k log2 k for k = 0..nfp (nfp: the disk's pixel count, < 65535);
 * g:   g[k] = f[k + 1] - f[k];
 * out: rows i0..i1-1 of the h x w map (row-major float64).
 *
 * For each pixel, with n = nfp - c_out the neighbours inside the image and T = sum over the 257
 * bins of f(count): E = (f(n) - T + f(c_out)) / n = log2 n - sum_b (c_b / n) log2 c_b. Moving the
 * disk one column changes two bins per footprint row; T follows through g. Values below 1e-9 are
 * float residue of an exact 0 (a one-value histogram) and are written as 0, as the numpy path does.
 */
#include <stdint.h>
#include <string.h>

#define NBINS 257

#if defined(_WIN32)
#define MEMLOG_EXPORT __declspec(dllexport)
#else
#define MEMLOG_EXPORT __attribute__((visibility("default")))
#endif

MEMLOG_EXPORT int memlog_entropy_version(void) { return 1; }

MEMLOG_EXPORT void memlog_entropy_rows(const uint16_t *pad, int64_t h, int64_t w, int64_t r,
                                       const int64_t *hw, const double *f, const double *g,
                                       int64_t i0, int64_t i1, double *out) {
    const int64_t pw = w + 2 * r, nr = 2 * r + 1;
    int64_t nfp = 0;
    uint16_t hist[NBINS];
    (void)h;
    for (int64_t d = 0; d < nr; d++) nfp += 2 * hw[d] + 1;
    for (int64_t i = i0; i < i1; i++) {
        double *o = out + (i - i0) * w;
        double t = 0.0;
        memset(hist, 0, sizeof(hist));
        /* the disk centred at column 0: padded column r; footprint row d is padded row i + d */
        for (int64_t d = 0; d < nr; d++) {
            const uint16_t *row = pad + (i + d) * pw + r;
            for (int64_t x = -hw[d]; x <= hw[d]; x++) hist[row[x]]++;
        }
        for (int b = 0; b < NBINS; b++) t += f[hist[b]];
        for (int64_t j = 0;; j++) {
            const int64_t co = hist[NBINS - 1], n = nfp - co;
            const double e = (f[n] - t + f[co]) / (double)n;
            o[j] = e < 1e-9 ? 0.0 : e;
            if (j + 1 == w) break;
            /* centre to column j + 1: row d loses column j - hw[d] and gains column j + hw[d] + 1 */
            for (int64_t d = 0; d < nr; d++) {
                const uint16_t *row = pad + (i + d) * pw + r + j;
                const uint16_t vr = row[-hw[d]], vi = row[hw[d] + 1];
                uint16_t c;
                if (vr == vi) continue;
                c = hist[vr];
                t -= g[c - 1];
                hist[vr] = (uint16_t)(c - 1);
                c = hist[vi];
                t += g[c];
                hist[vi] = (uint16_t)(c + 1);
            }
        }
    }
}
