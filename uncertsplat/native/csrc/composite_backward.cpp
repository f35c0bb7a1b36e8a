// The rasterizer's backward pass behind the C interface (kernels: composite.h).

#include "composite.h"

extern "C" {

int us_backward_f32(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, int64_t num_threads,
                    double alpha_min, double alpha_max, double t_min, int64_t F, int64_t G, int64_t M,
                    const float* gp, const float* feat, const int64_t* pair_gauss, const int64_t* tile_start,
                    const int64_t* tile_count, const float* t_final, const int32_t* last, const float* g_out,
                    float* g_pair, float* g_gauss) {
    US_PARAMS
    return backward_any<float>(F, prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, g_pair,
                              g_gauss);
}

int us_backward_f64(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, int64_t num_threads,
                    double alpha_min, double alpha_max, double t_min, int64_t F, int64_t G, int64_t M,
                    const double* gp, const double* feat, const int64_t* pair_gauss, const int64_t* tile_start,
                    const int64_t* tile_count, const double* t_final, const int32_t* last, const double* g_out,
                    double* g_pair, double* g_gauss) {
    US_PARAMS
    return backward_any<double>(F, prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, g_pair,
                              g_gauss);
}

}  // extern "C"
