// Speculative dynamic fetch (Aila, Laine & Karras 2012 addendum, their Kepler kernel):
// the refill of dynamic_fetch around the traversal of persistent_speculative_while_while.
// At the top of the warp loop, if fewer than SIMT_DYNAMIC_FETCH_THRESHOLD (20) lanes hold
// a ray, the idle lanes take __popc(idle) rays with one warp-aggregated atomic. Each outer
// iteration a lane reaching a leaf while it holds none postpones it and keeps traversing
// until every lane still traversing holds one; then the postponed leaves are intersected.
// A lane whose ray ends leaves the loop, so the refill test counts the lanes still tracing.
// Launch: blockDim.x a multiple of 32, any grid; *pool_next = 0 before the launch.
// any_hit != 0: stop at the first hit.
#include "common.cuh"

extern "C" __global__ void speculative_dynamic_fetch(
    const float4* __restrict__ nodes, const float4* __restrict__ woop,
    const int* __restrict__ tri_index, int root, const float4* __restrict__ ray_o,
    const float4* __restrict__ ray_d, int num_rays, int any_hit, int* __restrict__ hit_tri,
    float* __restrict__ hit_t, int* __restrict__ pool_next)
{
    // @block pool_fetch
    int ray = -1;  // -1: the lane holds no ray
    int node = SIMT_SENTINEL;
    int leaf = 0;  // < 0: the postponed leaf
    bool pool_empty = false;
    Ray r;
    int stack[SIMT_STACK_SIZE];
    int sp = 0;
    int hit_addr = -1;
    float t_best = 0.0f;
#pragma unroll 1
    while (true) {
        const unsigned idle = __ballot_sync(SIMT_FULL_MASK, ray < 0);
        // a dry warp (its fetch emptied the pool) skips the claim: its last visit
        // here runs pool_fetch alone
        if (!pool_empty) {
            // @block pool_claim
            if (__popc(~idle) < SIMT_DYNAMIC_FETCH_THRESHOLD) {
                const int base = simt_warp_fetch_add(pool_next, idle, SIMT_FULL_MASK);
                pool_empty = base + __popc(idle) >= num_rays;
                const int slot = base + __popc(idle & simt_lanemask_lt());
                if (ray < 0 && slot < num_rays) {
                    // @block ray_setup
                    ray = slot;
                    r = simt_load_ray(ray_o, ray_d, ray);
                    sp = 0;
                    stack[0] = SIMT_SENTINEL;
                    // a root leaf starts out postponed
                    leaf = root < 0 ? root : 0;
                    node = root < 0 ? SIMT_SENTINEL : root;
                    hit_addr = -1;
                    t_best = r.tmax;
                    // @block pool_claim
                }
            }
            // @block pool_fetch
        }
        if (__all_sync(SIMT_FULL_MASK, ray < 0)) break;
        // @block idle_wait
        if (ray < 0) continue;
        // @block loop_control
#pragma unroll 1
        while (ray >= 0) {
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
                // @block postpone
                if (node < 0 && leaf >= 0) {
                    leaf = node;
                    node = stack[sp--];
                }
                // @block trav_step
                if (!__any_sync(__activemask(), leaf >= 0)) break;
            }
            // @block leaf_entry
#pragma unroll 1
            while (leaf < 0) {
                int tri = ~leaf;
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
                leaf = node;
                if (node < 0) node = stack[sp--];
            }
            // @block finish
            if (node == SIMT_SENTINEL) {
                simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
                ray = -1;
                break;
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
