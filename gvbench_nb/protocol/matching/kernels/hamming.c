/* Hamming two-nearest kernel: every distance of two sets of binary descriptors once, keeping each
 * row's and each column's nearest index, smallest and second-smallest distance (the second equals the
 * first on a tie; ties go to the lower index). Plain C called through ctypes (no Python.h needed);
 * built by setuptools (pyproject.toml's ext-modules), compiled for three instruction sets and picked
 * at run time: AVX-512 with its vector popcount, the scalar popcount instruction, portable C. */
#include <stdint.h>

#define ARGS                                                                                          \
    const uint64_t *rows, const uint64_t *columns, int64_t n_rows, int64_t n_columns, int64_t words, \
        int32_t *distance, int32_t *row_nearest, int32_t *row_first, int32_t *row_second,             \
        int32_t *column_nearest, int32_t *column_first, int32_t *column_second

static inline __attribute__((always_inline)) void two_nearest_body(ARGS) {
    if (column_nearest)
        for (int64_t j = 0; j < n_columns; j++) {
            column_first[j] = column_second[j] = INT32_MAX;
            column_nearest[j] = 0;
        }
    for (int64_t i = 0; i < n_rows; i++) {
        const uint64_t *x = rows + i * words;
        /* One row's distances first, in a loop the compiler vectorises (4 words: ORB's 256 bits). */
        if (words == 4) {
            const uint64_t x0 = x[0], x1 = x[1], x2 = x[2], x3 = x[3];
            for (int64_t j = 0; j < n_columns; j++) {
                const uint64_t *y = columns + j * 4;
                distance[j] = __builtin_popcountll(x0 ^ y[0]) + __builtin_popcountll(x1 ^ y[1]) +
                              __builtin_popcountll(x2 ^ y[2]) + __builtin_popcountll(x3 ^ y[3]);
            }
        } else {
            for (int64_t j = 0; j < n_columns; j++) {
                const uint64_t *y = columns + j * words;
                int32_t d = 0;
                for (int64_t w = 0; w < words; w++) d += __builtin_popcountll(x[w] ^ y[w]);
                distance[j] = d;
            }
        }
        if (column_nearest) {
            /* Branch-free, so it vectorises; rows arrive in order, so a strict < keeps the lower row. */
            const int32_t row = (int32_t)i;
            for (int64_t j = 0; j < n_columns; j++) {
                const int32_t d = distance[j], first = column_first[j];
                const int32_t above = d > first ? d : first;
                column_second[j] = column_second[j] < above ? column_second[j] : above;
                column_nearest[j] = d < first ? row : column_nearest[j];
                column_first[j] = d < first ? d : first;
            }
        }
        int32_t first = INT32_MAX, second = INT32_MAX, nearest = 0;
        for (int64_t j = 0; j < n_columns; j++) {
            const int32_t d = distance[j];
            if (d < first) {
                second = first;
                first = d;
                nearest = (int32_t)j;
            } else if (d < second) {
                second = d;
            }
        }
        row_nearest[i] = nearest;
        row_first[i] = first;
        row_second[i] = second;
    }
}

static void two_nearest_portable(ARGS) {
    two_nearest_body(rows, columns, n_rows, n_columns, words, distance, row_nearest, row_first, row_second,
                     column_nearest, column_first, column_second);
}

#if defined(__x86_64__) || defined(__i386__)
__attribute__((target("popcnt"))) static void two_nearest_popcnt(ARGS) {
    two_nearest_body(rows, columns, n_rows, n_columns, words, distance, row_nearest, row_first, row_second,
                     column_nearest, column_first, column_second);
}

__attribute__((target("avx512f,avx512bw,avx512vl,avx512vpopcntdq,popcnt"))) static void two_nearest_avx512(ARGS) {
    two_nearest_body(rows, columns, n_rows, n_columns, words, distance, row_nearest, row_first, row_second,
                     column_nearest, column_first, column_second);
}
#endif

/* The widest instruction set this CPU runs, capped at `widest` (0 portable, 1 popcount, 2 AVX-512):
 * the cap lets the tests run every path on one machine. */
int hamming_instruction_set(int widest) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    if (widest >= 2 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
        __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512vpopcntdq"))
        return 2;
    if (widest >= 1 && __builtin_cpu_supports("popcnt")) return 1;
#endif
    (void)widest;
    return 0;
}

/* rows (n_rows, words) and columns (n_columns, words) uint64; distance: n_columns int32 of scratch;
 * the column outputs may be NULL (the one-way rule needs none). */
void hamming_two_nearest(ARGS, int instruction_set) {
#if defined(__x86_64__) || defined(__i386__)
    if (instruction_set == 2) {
        two_nearest_avx512(rows, columns, n_rows, n_columns, words, distance, row_nearest, row_first, row_second,
                           column_nearest, column_first, column_second);
        return;
    }
    if (instruction_set == 1) {
        two_nearest_popcnt(rows, columns, n_rows, n_columns, words, distance, row_nearest, row_first, row_second,
                           column_nearest, column_first, column_second);
        return;
    }
#endif
    (void)instruction_set;
    two_nearest_portable(rows, columns, n_rows, n_columns, words, distance, row_nearest, row_first, row_second,
                         column_nearest, column_first, column_second);
}
