// The rasterizer's backward pass behind the C interface (kernels: composite.h), for float (_f32) and double
// (_f64), defined once by a macro over the scalar type.

#include "composite.h"

extern "C" {

#define US_BACKWARD(SUFFIX, S)                                                                                   \
    int us_backward_##SUFFIX(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size,      \
                             int64_t num_threads, double alpha_min, double alpha_max, double t_min, int64_t F,  \
                             int64_t G, int64_t M, const S* gp, const S* feat, const int32_t* pair_gauss,       \
                             const int64_t* tile_start, const int64_t* tile_count, const S* t_final,            \
                             const int32_t* last, const S* g_out, S* g_pair, S* g_gauss) {                      \
        US_PARAMS                                                                                                \
        return backward_any<S>(F, prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, \
                               g_pair, g_gauss);                                                                 \
    }
US_BACKWARD(f32, float)
US_BACKWARD(f64, double)

// The backward of us_forward_image: d loss / d rgb, depth, alpha (each may be null: 0) -> per-pair rows
// g_pair [M, 11] (scratch) and per-Gaussian sums g_gauss [11 G] in blocks: means [G, 2], conics [G, 3], log
// opacities [G], colours [G, 3], depths [G], and the constant feature's [G] (unused) (composite.h, PLANAR_START).
#define US_BACKWARD_IMAGE(SUFFIX, S)                                                                             \
    int us_backward_image_##SUFFIX(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, \
                                   int64_t num_threads, double alpha_min, double alpha_max, double t_min,       \
                                   int64_t F, int64_t G, int64_t M, int64_t height, int64_t width,              \
                                   const S* means2d, const S* conics, const S* log_o, const S* colors,          \
                                   const S* depths, const S* background, const int32_t* pair_gauss,             \
                                   const int64_t* tile_start, const int64_t* tile_count, const S* t_final,      \
                                   const int32_t* last, const S* g_rgb, const S* g_depth, const S* g_alpha,     \
                                   S* g_pair, S* g_gauss) {                                                     \
        if (F != IMAGE_F) return 1;                                                                              \
        US_PARAMS                                                                                                \
        ImageIO<S> io = image_inputs<S>(means2d, conics, log_o, colors, depths, height, width, background);      \
        io.g_rgb = g_rgb, io.g_depth = g_depth, io.g_alpha = g_alpha;                                           \
        return backward_image<S>(prm, G, M, io, pair_gauss, tile_start, tile_count, t_final, last, g_pair,       \
                                 g_gauss);                                                                       \
    }
US_BACKWARD_IMAGE(f32, float)
US_BACKWARD_IMAGE(f64, double)

}  // extern "C"
