// The rasterizer's backward pass behind the C interface (kernels: composite.h), for float (_f32) and double
// (_f64), defined once by a macro over the scalar type.

#include "composite.h"

extern "C" {

#define US_BACKWARD(SUFFIX, S)                                                                                   \
    int us_backward_##SUFFIX(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size,      \
                             int64_t num_threads, double alpha_min, double alpha_max, double t_min, int64_t F,  \
                             int64_t G, int64_t M, const S* gp, const S* feat, const int64_t* pair_gauss,       \
                             const int64_t* tile_start, const int64_t* tile_count, const S* t_final,            \
                             const int32_t* last, const S* g_out, S* g_pair, S* g_gauss) {                      \
        US_PARAMS                                                                                                \
        return backward_any<S>(F, prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, \
                               g_pair, g_gauss);                                                                 \
    }
US_BACKWARD(f32, float)
US_BACKWARD(f64, double)

}  // extern "C"
