/* kNN refinement's vote on the CPU, 16 points at a time in vector lanes.
 *
 * For every point with a pixel: the S x S window of the padded range image around its pixel
 * (the centre left out), each neighbour's distance |range - point's range| * (1 - Gaussian
 * weight) in float32 exactly as the published code rounds it, the k - 1 nearest kept in a sorted
 * list (ties in window order: an equal distance goes behind those already in), those beyond the
 * cutoff dropped, and a majority vote of their classes and the centre's. The class codes are
 * C + 1 - class for a class that votes and 0 for one that does not; a vote's score is
 * count * (C + 2) + code, so the largest is the most votes, then the lowest class.
 *
 * The body (knn_vote_body.h) is compiled three times: for AVX-512 (16 points a vector), AVX2 (8)
 * and the baseline of the compiler's target (4); `rangeret_knn_vote` picks the best the CPU
 * runs. Written with GCC vector types, so each lane is one point and every step is the same
 * instruction for all lanes; no fused multiply-add may round differently, hence
 * -ffp-contract=off in the build.
 */
#include <stdint.h>
#include <string.h>

/* The most neighbours one point keeps (k - 1); the caller checks it against `rangeret_knn_slots`. */
#define MAX_SLOTS 64

/* The lanes of a where mask m is set, of b elsewhere. */
#define PICK(m, a, b) (((m) & (a)) | (~(m) & (b)))

#if defined(__x86_64__) || defined(__i386__)
#define X86 1
#include <immintrin.h>
#endif

/* Each variant: TARGET the instruction set it is compiled for, LANES points per vector, VF / VI
 * its float and int32 vector types, GATHER_PS / GATHER_EPI32 one value per lane from a base and
 * an index vector, KERNEL the function's name. */
typedef float vf4 __attribute__((vector_size(16)));
typedef int32_t vi4 __attribute__((vector_size(16)));

static inline vf4 gather_ps_4(const float *base, vi4 at) {
    vf4 v;
    for (int l = 0; l < 4; ++l) v[l] = base[at[l]];
    return v;
}

static inline vi4 gather_epi32_4(const int32_t *base, vi4 at) {
    vi4 v;
    for (int l = 0; l < 4; ++l) v[l] = base[at[l]];
    return v;
}

#define TARGET
#define LANES 4
#define VF vf4
#define VI vi4
#define GATHER_PS gather_ps_4
#define GATHER_EPI32 gather_epi32_4
#define KERNEL vote_baseline
#include "knn_vote_body.h"

#ifdef X86
typedef float vf8 __attribute__((vector_size(32)));
typedef int32_t vi8 __attribute__((vector_size(32)));
typedef float vf16 __attribute__((vector_size(64)));
typedef int32_t vi16 __attribute__((vector_size(64)));

#define TARGET __attribute__((target("avx2")))
#define LANES 8
#define VF vf8
#define VI vi8
#define GATHER_PS(base, at) ((vf8)_mm256_i32gather_ps((base), (__m256i)(at), 4))
#define GATHER_EPI32(base, at) ((vi8)_mm256_i32gather_epi32((const int *)(base), (__m256i)(at), 4))
#define KERNEL vote_avx2
#include "knn_vote_body.h"

#define TARGET __attribute__((target("avx512f")))
#define LANES 16
#define VF vf16
#define VI vi16
#define GATHER_PS(base, at) ((vf16)_mm512_i32gather_ps((__m512i)(at), (base), 4))
#define GATHER_EPI32(base, at) ((vi16)_mm512_i32gather_epi32((__m512i)(at), (base), 4))
#define KERNEL vote_avx512
#include "knn_vote_body.h"
#endif

/* The version of these functions' arguments (knn_native.ABI must be the same). */
int32_t rangeret_knn_abi(void) { return 1; }

/* The most neighbours a point may keep. */
int32_t rangeret_knn_slots(void) { return MAX_SLOTS; }

/* The best instruction set this CPU runs: 3 AVX-512, 2 AVX2, 1 the baseline. */
int32_t rangeret_knn_best_isa(void) {
#ifdef X86
    if (__builtin_cpu_supports("avx512f")) return 3;
    if (__builtin_cpu_supports("avx2")) return 2;
#endif
    return 1;
}

/* Classes of points start..stop into out (points with proj_x < 0 left as they are), with the
 * instruction set `isa` (0: the best this CPU runs). `far` and `codes` are the range image
 * (empty pixels +inf, padding 0) and its class codes padded by `pad` on every side, rows of
 * width + 2 pad values; `offsets` and `weights` the `size` neighbours' offsets from the centre
 * and their weights; `cutoff` applies where `use_cutoff`. Returns 0; -1 for more than
 * MAX_SLOTS neighbours kept, -2 for an instruction set this CPU lacks, -3 for a pixel outside
 * the image (nothing is read there; `out` may be partly written). */
int32_t rangeret_knn_vote(
    int32_t isa, const float *far, const int32_t *codes, int32_t height, int32_t width,
    int32_t pad, const int32_t *offsets, const float *weights, int32_t size, const float *ranges,
    const int64_t *proj_x, const int64_t *proj_y, int64_t start, int64_t stop, int32_t wanted,
    int32_t use_cutoff, float cutoff, int32_t num_classes, int32_t votes_from, int64_t *out)
{
    if ((wanted < size ? wanted : size) > MAX_SLOTS) return -1;
    const int32_t best = rangeret_knn_best_isa();
    if (isa == 0) isa = best;
    if (isa > best || isa < 1) return -2;
#define ARGS far, codes, height, width, pad, offsets, weights, size, ranges, proj_x, proj_y, \
             start, stop, wanted, use_cutoff, cutoff, num_classes, votes_from, out
#ifdef X86
    if (isa == 3) return vote_avx512(ARGS);
    if (isa == 2) return vote_avx2(ARGS);
#endif
    return vote_baseline(ARGS);
#undef ARGS
}
