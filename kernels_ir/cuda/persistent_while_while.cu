// Persistent while-while (Aila & Laine 2009): launch only as many warps as the GPU
// holds; each warp takes 32 rays from a global pool with one atomicAdd when all of its
// lanes are done, and traces them with the while-while loop.
// Launch: blockDim.x a multiple of 32, any grid; *pool_next = 0 before the launch.
// any_hit != 0: stop at the first hit.
#include "common.cuh"

extern "C" __global__ void persistent_while_while(const float4* __restrict__ nodes,
                                                  const float4* __restrict__ woop,
                                                  const int* __restrict__ tri_index, int root,
                                                  const float4* __restrict__ ray_o,
                                                  const float4* __restrict__ ray_d,
                                                  int num_rays, int any_hit,
                                                  int* __restrict__ hit_tri,
                                                  float* __restrict__ hit_t,
                                                  int* __restrict__ pool_next)
{
#pragma unroll 1
    while (true) {
        // @block pool_fetch
        int base = 0;
        if (simt_lane_id() == 0) base = atomicAdd(pool_next, SIMT_WARP_SIZE);
        base = __shfl_sync(SIMT_FULL_MASK, base, 0);
        if (base >= num_rays) break;
        const int ray = base + (int)simt_lane_id();
        // @block idle_wait
        if (ray < num_rays) {
            // @block ray_setup
            const Ray r = simt_load_ray(ray_o, ray_d, ray);
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
                            if (simt_opaque(any_hit)) {
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
            // @block finish
            simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
            // @block pool_fetch
        }
    }
    // @end
}
