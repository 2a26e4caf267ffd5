// Persistent while-while on the compressed 8-wide BVH (cwbvh.cuh, layout "cwbvh" of
// simt_sim/bvh/cwbvh.py): Ylitie, Karras & Laine's (HPG 2017) traversal loop in the visiting
// order of simt_sim/bvh/cwbvh_traverse.py, fed by persistent_while_while's pool (each warp
// takes 32 rays with one atomicAdd when all of its lanes are done).
// One iteration of the trace loop: take the next child of the current node group (pushing
// the rest of the group when it still has hits), test that node's 8 child boxes (its
// interior hits become the node group, its leaf hits the triangle group), test the
// triangle group lowest bit first, then pop a node group when the current one is empty;
// the ray ends when it is empty and the stack too (any_hit != 0: at the first hit).
// Push and pop are branch free (a store or load every iteration, the stack pointer moved by
// the predicate), so an iteration's instructions depend only on the size of its triangle
// group, how its triangle loop ends and whether the ray goes on: the op stream says that
// much (the leaf children hit are its LEAF ops), not which hit children are interior.
// The triangle loop sits in an `if` of its own (leaf_entry) so that the build charges its
// exit once per loop run, not per triangle; the pop past the exit test is stack_pop.
// Launch: blockDim.x a multiple of 32, any grid; *pool_next = 0 before the launch.
// The tree's WideStats.depth must be < 64 (SIMT_CWBVH_STACK_SIZE node groups per ray).
#include "common.cuh"
#include "cwbvh.cuh"

extern "C" __global__ void cwbvh_persistent_while_while(const float4* __restrict__ nodes,
                                                        const float4* __restrict__ woop,
                                                        const int* __restrict__ tri_index,
                                                        int root,
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
            const unsigned octant = (r.idir.x < 0.0f ? 1u : 0u) | (r.idir.y < 0.0f ? 2u : 0u) |
                                    (r.idir.z < 0.0f ? 4u : 0u);
            CwGroup stack[SIMT_CWBVH_STACK_SIZE];
            int sp = 0;
            // the root: node `root` (0) alone, slot 0 of a virtual parent
            CwGroup g;
            g.base = (unsigned)root;
            g.bits = (1u << 8) | (1u << octant);
            int hit_addr = -1;
            float t_best = r.tmax;
            // @block loop_control
#pragma unroll 1
            while (true) {
                // @block trav_step
                const unsigned hits = g.bits & 0xffu;
                const unsigned imask = g.bits >> 8;
                const unsigned slot = (unsigned)(__ffs(hits) - 1) ^ octant;
                const unsigned node = g.base + __popc(imask & ((1u << slot) - 1u));
                const unsigned rest = hits & (hits - 1u);
                stack[sp].base = g.base;
                stack[sp].bits = (imask << 8) | rest;
                sp += rest != 0u ? 1 : 0;
                const CwHit h = simt_cw_intersect_node(nodes, node, r, octant, t_best);
                g.base = h.base;
                g.bits = (h.imask << 8) | h.node_hits;
                unsigned tri_hits = h.tri_hits;
                // @block leaf_entry
                if (tri_hits != 0u) {
                    // @block tri_test
#pragma unroll 1
                    do {
                        const int b = __ffs(tri_hits) - 1;
                        tri_hits &= tri_hits - 1u;
                        const int tri = 3 * ((int)h.tri_base + b);
                        const float4 w0 = __ldg(woop + tri);
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
                                g.bits = 0u;
                                sp = 0;
                                break;
                            }
                        }
                        // @block tri_test
                    } while (tri_hits != 0u);
                    // @block leaf_entry
                }
                // @block loop_control
                const bool pop = (g.bits & 0xffu) == 0u;
                if (pop && sp == 0) break;
                // @block stack_pop
                sp -= pop ? 1 : 0;
                const CwGroup e = stack[sp];
                g.base = pop ? e.base : g.base;
                g.bits = pop ? e.bits : g.bits;
            }
            // @block finish
            simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
            // @block pool_fetch
        }
    }
    // @end
}
