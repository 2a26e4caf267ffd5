// Wavefront path tracing, stage 3 of 4: shade the extension queue's hits, one thread per
// entry. A hit on the diffuse surface (albedo `albedo`) pushes a shadow ray to a uniform
// point of the area light into the connect queue, and, unless Russian roulette (after
// bounce 2) or max_bounces ends the path, a cosine-weighted extension ray into the next
// extension queue. Queue pushes are warp-aggregated: one atomicAdd per warp and queue.
// A path that ends stores its number of hits in path_length.
// Launch: any grid covering the queue's capacity; *out_count and *c_count zeroed before.
#include "common.cuh"

extern "C" __global__ void wavefront_shade(
    const float4* __restrict__ woop, const float4* __restrict__ q_o,
    const float4* __restrict__ q_d, const int* __restrict__ q_path,
    const int* __restrict__ q_count, const int* __restrict__ q_hit_addr,
    const float* __restrict__ q_hit_t, AreaLight light, float albedo, float eps,
    int max_bounces, float4* __restrict__ path_thr, unsigned* __restrict__ path_rng,
    int* __restrict__ path_bounce, int* __restrict__ path_length, float4* __restrict__ out_o,
    float4* __restrict__ out_d, int* __restrict__ out_path, int* __restrict__ out_count,
    float4* __restrict__ c_o, float4* __restrict__ c_d, int* __restrict__ c_path,
    float4* __restrict__ c_contrib, int* __restrict__ c_count)
{
    // @block shade
    const int entry = blockIdx.x * blockDim.x + threadIdx.x;
    if (entry >= *q_count) return;
    const int path = __ldg(q_path + entry);
    const int addr = __ldg(q_hit_addr + entry);
    int bounce = path_bounce[path];
    bool shadow = false;
    bool extend = false;
    float4 so, sd, eo, ed;
    float3 nee;
    if (addr >= 0) {
        const float4 o = __ldg(q_o + entry);
        const float4 d = __ldg(q_d + entry);
        const PathVertex pv = simt_hit_vertex(woop, addr, o, d, __ldg(q_hit_t + entry));
        unsigned rng = path_rng[path];
        const float4 t4 = path_thr[path];
        float3 thr = simt_f3(t4);
        ++bounce;
        const float l1 = simt_rand(rng);
        const float l2 = simt_rand(rng);
        shadow = simt_sample_light(light, pv, thr, albedo, eps, l1, l2, &so, &sd, &nee);
        const float b1 = simt_rand(rng);
        const float b2 = simt_rand(rng);
        const float3 dir = simt_sample_cosine(pv.normal, b1, b2);
        thr = make_float3(thr.x * albedo, thr.y * albedo, thr.z * albedo);
        extend = bounce < max_bounces && simt_roulette(bounce, &thr, simt_rand(rng));
        eo = make_float4(pv.pos.x, pv.pos.y, pv.pos.z, eps);
        ed = make_float4(dir.x, dir.y, dir.z, SIMT_INF);
        path_rng[path] = rng;
        path_thr[path] = make_float4(thr.x, thr.y, thr.z, t4.w);
        path_bounce[path] = bounce;
    }
    // @block queue_push
    const unsigned lanes = __activemask();
    const unsigned want_c = __ballot_sync(lanes, shadow);
    if (want_c != 0u) {
        const int base = simt_warp_fetch_add(c_count, want_c, lanes);
        if (shadow) {
            const int slot = base + __popc(want_c & simt_lanemask_lt());
            c_o[slot] = so;
            c_d[slot] = sd;
            c_path[slot] = path;
            c_contrib[slot] = make_float4(nee.x, nee.y, nee.z, 0.0f);
        }
    }
    const unsigned want_e = __ballot_sync(lanes, extend);
    if (want_e != 0u) {
        const int base = simt_warp_fetch_add(out_count, want_e, lanes);
        if (extend) {
            const int slot = base + __popc(want_e & simt_lanemask_lt());
            out_o[slot] = eo;
            out_d[slot] = ed;
            out_path[slot] = path;
        }
    }
    // @block finish
    if (!extend) path_length[path] = bounce;
    // @end
}
