// Wavefront path tracing (Laine, Karras & Aila 2013), stage 1 of 4: start one path per
// primary ray and put its ray in the extension queue.
// Path state (global, one entry per path): path_thr = throughput (r, g, b, 0), path_rng =
// random state, path_bounce = hits so far; outputs radiance (r, g, b, 1) and
// path_length are zeroed here and filled by the later stages.
// Queue: q_o/q_d (ray layout of common.cuh), q_path = owning path, *q_count = length.
// Host loop: generate; then while the extension queue is not empty: extend, shade
// (into the other extension queue and the connect queue, counts zeroed before), connect.
// Launch: any grid covering num_paths threads.
#include "common.cuh"

extern "C" __global__ void wavefront_generate(const float4* __restrict__ cam_o,
                                              const float4* __restrict__ cam_d, int num_paths,
                                              unsigned seed, float4* __restrict__ q_o,
                                              float4* __restrict__ q_d, int* __restrict__ q_path,
                                              int* __restrict__ q_count,
                                              float4* __restrict__ path_thr,
                                              unsigned* __restrict__ path_rng,
                                              int* __restrict__ path_bounce,
                                              float4* __restrict__ radiance,
                                              int* __restrict__ path_length)
{
    // @block ray_setup
    const int path = blockIdx.x * blockDim.x + threadIdx.x;
    if (path >= num_paths) return;
    const float4 o = __ldg(cam_o + path);
    const float4 d = __ldg(cam_d + path);
    path_thr[path] = make_float4(1.0f, 1.0f, 1.0f, 0.0f);
    path_rng[path] = simt_rng_init(path, seed);
    path_bounce[path] = 0;
    radiance[path] = make_float4(0.0f, 0.0f, 0.0f, 1.0f);
    path_length[path] = 0;
    // @block queue_push
    if (path == 0) *q_count = num_paths;  // every path enters the queue, in path order
    q_o[path] = o;
    q_d[path] = d;
    q_path[path] = path;
    // @end
}
