// Dynamic fetch (Aila, Laine & Karras 2012 addendum): persistent warps whose terminated
// lanes take new rays from the global pool as soon as fewer than
// SIMT_DYNAMIC_FETCH_THRESHOLD (20) of the 32 lanes are still tracing; one atomicAdd per
// refill, for __popc(lanes needing a ray) rays. Each lane traces with while-while.
// Launch: blockDim.x a multiple of 32, any grid; *pool_next = 0 before the launch.
// any_hit != 0: stop at the first hit.
#include "common.cuh"

extern "C" __global__ void dynamic_fetch(const float4* __restrict__ nodes,
                                         const float4* __restrict__ woop,
                                         const int* __restrict__ tri_index, int root,
                                         const float4* __restrict__ ray_o,
                                         const float4* __restrict__ ray_d, int num_rays,
                                         int any_hit, int* __restrict__ hit_tri,
                                         float* __restrict__ hit_t, int* __restrict__ pool_next)
{
    // @block pool_fetch
    int ray = -1;
    int node = SIMT_SENTINEL;  // SIMT_SENTINEL: the lane holds no ray
    bool pool_empty = false;
    Ray r;
    int stack[SIMT_STACK_SIZE];
    int sp = 0;
    int hit_addr = -1;
    float t_best = 0.0f;
#pragma unroll 1
    while (true) {
        const unsigned idle = __ballot_sync(SIMT_FULL_MASK, node == SIMT_SENTINEL);
        // a dry warp (its fetch emptied the pool) skips the claim: its last visit
        // here runs pool_fetch alone
        if (!pool_empty) {
            // @block pool_claim
            if (__popc(~idle) < SIMT_DYNAMIC_FETCH_THRESHOLD) {
                const int base = simt_warp_fetch_add(pool_next, idle, SIMT_FULL_MASK);
                pool_empty = base + __popc(idle) >= num_rays;
                const int slot = base + __popc(idle & simt_lanemask_lt());
                if (node == SIMT_SENTINEL && slot < num_rays) {
                    // @block ray_setup
                    ray = slot;
                    r = simt_load_ray(ray_o, ray_d, ray);
                    sp = 0;
                    stack[0] = SIMT_SENTINEL;
                    node = root;
                    hit_addr = -1;
                    t_best = r.tmax;
                    // @block pool_claim
                }
            }
            // @block pool_fetch
        }
        if (__all_sync(SIMT_FULL_MASK, node == SIMT_SENTINEL)) break;
        // @block idle_wait
        if (node == SIMT_SENTINEL) continue;
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
            // @block finish
            if (node == SIMT_SENTINEL) {
                simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
                break;  // so that the lanes counted below are those still holding a ray
            }
            // @block refill_test
            const bool refill =
                !pool_empty && __popc(__activemask()) < SIMT_DYNAMIC_FETCH_THRESHOLD;
            // @block refill_break
            if (refill) break;
        }
        // @block pool_fetch
    }
    // @end
}
