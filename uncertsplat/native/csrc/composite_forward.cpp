// The rasterizer's binning and forward pass behind the C interface (kernels: composite.h). Each entry point
// exists for float (_f32) and double (_f64), defined once by a macro over the scalar type.

#include "composite.h"

extern "C" {

// Interface version: native.py refuses a library whose version differs from its own.
int us_version() { return 21; }

int us_max_features() { return 8; }

#define US_FORWARD(SUFFIX, S)                                                                                    \
    int us_forward_##SUFFIX(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size,       \
                            int64_t num_threads, double alpha_min, double alpha_max, double t_min, int64_t F,   \
                            int64_t G, const S* gp, const S* feat, const int32_t* pair_gauss,                   \
                            const int64_t* tile_start, const int64_t* tile_count, S* out, S* t_final,           \
                            int32_t* last) {                                                                    \
        US_PARAMS                                                                                                \
        return forward_any<S>(F, prm, G, gp, feat, pair_gauss, tile_start, tile_count, out, t_final, last);     \
    }
US_FORWARD(f32, float)
US_FORWARD(f64, double)

// render()'s compositing in image layout (composite.h, ImageIO): F must be 5; background [3] or null.
#define US_FORWARD_IMAGE(SUFFIX, S)                                                                              \
    int us_forward_image_##SUFFIX(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, \
                                  int64_t num_threads, double alpha_min, double alpha_max, double t_min,        \
                                  int64_t F, int64_t G, int64_t height, int64_t width, const S* means2d,        \
                                  const S* conics, const S* log_o, const S* colors, const S* depths,            \
                                  const S* background, const int32_t* pair_gauss, const int64_t* tile_start,    \
                                  const int64_t* tile_count, S* rgb, S* depth, S* alpha, S* t_final,            \
                                  int32_t* last) {                                                              \
        if (F != IMAGE_F) return 1;                                                                              \
        US_PARAMS                                                                                                \
        ImageIO<S> io = image_inputs<S>(means2d, conics, log_o, colors, depths, height, width, background);      \
        io.rgb = rgb, io.depth = depth, io.alpha = alpha;                                                       \
        return forward_image<S>(prm, G, io, pair_gauss, tile_start, tile_count, t_final, last);                  \
    }
US_FORWARD_IMAGE(f32, float)
US_FORWARD_IMAGE(f64, double)

// Binning, in two calls. us_bin_count: the depth order of the valid entries (order [G], num_visible),
// per-worker tile counts [workers, T]; returns the number of pairs M (-1 when out of memory) and, in
// *state, what it found, which us_bin_fill consumes: with tile_start [T] (cumulative sum of the counts
// summed over workers) it writes pair_gauss [M] and, unless that pointer is null, pair_tile [M], and frees
// the state. us_bin_free frees a state that will not be filled.
#define US_BIN_ARGS BinArgs args{G, N, C, width, height, tile_size, tiles_x, tiles_y, workers, alpha_min};
#define US_BIN_HEAD                                                                                             \
    int64_t G, int64_t N, int64_t C, int64_t width, int64_t height, int64_t tile_size, int64_t tiles_x,       \
        int64_t tiles_y, int64_t workers, double alpha_min

#define US_BIN(SUFFIX, S)                                                                                        \
    int64_t us_bin_count_##SUFFIX(US_BIN_HEAD, const S* means2d, const S* extents, const S* conics,             \
                                  const S* opac, const S* depths, const uint8_t* valid, int64_t* order,         \
                                  int64_t* num_visible, int64_t* counts, void** state) {                        \
        US_BIN_ARGS                                                                                              \
        return bin_count_any<S>(args, means2d, extents, conics, opac, depths, valid, order, num_visible, counts, \
                                state);                                                                          \
    }                                                                                                            \
    int us_bin_fill_##SUFFIX(US_BIN_HEAD, const S* means2d, const S* extents, const S* conics, const S* opac,    \
                             const int64_t* order, int64_t num_visible, const int64_t* counts,                  \
                             const int64_t* tile_start, int32_t* pair_gauss, int64_t* pair_tile, void* state) { \
        US_BIN_ARGS                                                                                              \
        (void)extents;                                                                                           \
        return bin_fill_any<S>(args, means2d, conics, opac, order, num_visible, state, counts, tile_start,       \
                               pair_gauss, pair_tile);                                                           \
    }
US_BIN(f32, float)
US_BIN(f64, double)

void us_bin_free(void* state) { delete static_cast<BinState*>(state); }

}  // extern "C"
