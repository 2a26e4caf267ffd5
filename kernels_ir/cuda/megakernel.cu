// Path-tracing megakernel (Laine, Karras & Aila 2013): one thread follows one path for
// its whole life. Each loop iteration traces one ray with while-while traversal: an
// extension ray (closest hit) or the shadow ray of next-event estimation (any hit). At a
// hit the diffuse surface (albedo `albedo`) is shaded: a shadow ray to a uniform point of
// the area light, a cosine-weighted extension ray, Russian roulette after bounce 2, at
// most `max_bounces` hits. Only light reached through a shadow ray counts (the light is
// not part of the BVH).
// Inputs: primary rays cam_o/cam_d (ray layout of common.cuh), one path each.
// Outputs: radiance[path] = (r, g, b, 1), path_length[path] = number of hits.
// Launch: any grid covering num_paths threads.
#include "common.cuh"

extern "C" __global__ void megakernel(const float4* __restrict__ nodes,
                                      const float4* __restrict__ woop, int root,
                                      const float4* __restrict__ cam_o,
                                      const float4* __restrict__ cam_d, int num_paths,
                                      AreaLight light, float albedo, float eps, unsigned seed,
                                      int max_bounces, float4* __restrict__ radiance,
                                      int* __restrict__ path_length)
{
    // @block ray_setup
    const int path = blockIdx.x * blockDim.x + threadIdx.x;
    if (path >= num_paths) return;
    unsigned rng = simt_rng_init(path, seed);
    float4 o = __ldg(cam_o + path);  // the ray traced next
    float4 d = __ldg(cam_d + path);
    float4 next_o = o;               // the extension ray that follows a shadow ray
    float4 next_d = d;
    float3 thr = make_float3(1.0f, 1.0f, 1.0f);
    float3 rad = make_float3(0.0f, 0.0f, 0.0f);
    float3 nee = rad;                // what the pending shadow ray brings if unoccluded
    int bounce = 0;
    bool shadow = false;             // the ray traced next is a shadow ray
    bool extend = true;              // an extension ray follows the shadow ray
    // @block loop_control
#pragma unroll 1
    while (true) {
        // @block ray_setup
        const Ray r = simt_make_ray(o, d);
        int stack[SIMT_STACK_SIZE];
        int sp = 0;
        stack[0] = SIMT_SENTINEL;
        int node = root;
        int hit_addr = -1;
        float t_best = r.tmax;
        // @block loop_control
#pragma unroll 1
        while (node != SIMT_SENTINEL) {
            // @block trav_step
#pragma unroll 1
            while (simt_is_interior(node)) {
                const NodeHit h = simt_intersect_node(nodes, node, r, t_best);
                if (h.hit0 && h.hit1) {
                    // @block trav_both
                    const bool swap = h.c1min < h.c0min;
                    node = swap ? h.child1 : h.child0;
                    stack[++sp] = swap ? h.child0 : h.child1;
                    // @block trav_step
                } else {
                    // @block trav_else
                    if (h.hit0 || h.hit1) {
                        // @block trav_one
                        node = h.hit0 ? h.child0 : h.child1;
                        // @block trav_else
                    } else {
                        // @block trav_none
                        node = stack[sp--];
                        // @block trav_else
                    }
                    // @block trav_step
                }
            }
            // @block leaf_entry
#pragma unroll 1
            while (node < 0) {
                int tri = ~node;
                node = stack[sp--];
                // @block tri_test
#pragma unroll 1
                for (;; tri += 3) {
                    const float4 w0 = __ldg(woop + tri);
                    if (simt_is_tri_end(w0)) break;
                    SimtWoop s;
                    bool hit = simt_woop_t(w0, r, t_best, &s);
                    if (hit) {
                        // @block tri_u
                        hit = simt_woop_u(woop, tri, w0, r, &s);
                        if (hit) {
                            // @block tri_v
                            hit = simt_woop_v(woop, tri, r, &s);
                            // @block tri_u
                        }
                        // @block tri_test
                    }
                    const float t = s.t;
                    // @block tri_hit
                    if (hit) {
                        t_best = t;
                        hit_addr = tri;
                        if (shadow) {
                            node = SIMT_SENTINEL;
                            break;
                        }
                    }
                    // @block tri_test
                }
                // @block leaf_entry
            }
            // @block loop_control
        }
        // @block shade
        if (shadow) {
            if (hit_addr < 0) rad = make_float3(rad.x + nee.x, rad.y + nee.y, rad.z + nee.z);
            shadow = false;
            if (!extend) break;
            o = next_o;
            d = next_d;
            continue;
        }
        if (hit_addr < 0) break;
        const PathVertex pv = simt_hit_vertex(woop, hit_addr, o, d, t_best);
        ++bounce;
        const float l1 = simt_rand(rng);
        const float l2 = simt_rand(rng);
        shadow = simt_sample_light(light, pv, thr, albedo, eps, l1, l2, &o, &d, &nee);
        const float b1 = simt_rand(rng);
        const float b2 = simt_rand(rng);
        const float3 dir = simt_sample_cosine(pv.normal, b1, b2);
        thr = make_float3(thr.x * albedo, thr.y * albedo, thr.z * albedo);
        extend = bounce < max_bounces && simt_roulette(bounce, &thr, simt_rand(rng));
        next_o = make_float4(pv.pos.x, pv.pos.y, pv.pos.z, eps);
        next_d = make_float4(dir.x, dir.y, dir.z, SIMT_INF);
        if (!shadow) {
            if (!extend) break;
            o = next_o;
            d = next_d;
        }
        // @block loop_control
    }
    // @block finish
    radiance[path] = make_float4(rad.x, rad.y, rad.z, 1.0f);
    path_length[path] = bounce;
    // @end
}
