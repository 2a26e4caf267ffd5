// while-while traversal (Aila & Laine 2009) of the 4-wide BVH (bvh4.cuh, layout "bvh4" of
// simt_sim/bvh/wide.py): one thread per ray, its own stack;
//   while ray not terminated { while node is interior: traverse;
//                              while node is a leaf: intersect its triangles }
// A traversal step tests the node's 4 child boxes; with k children hit it pops (k = 0),
// goes to the one (k = 1), or orders them by tnear, goes to the nearest and pushes the
// other k - 1 farthest first (k >= 2), the order of simt_sim/bvh/wide_traverse.py.
// Launch: any grid covering num_rays threads. any_hit != 0: stop at the first hit.
// Per-ray stacks hold SIMT_BVH4_STACK_SIZE (192) entries: the tree's WideStats.depth
// must be < 64.
#include "common.cuh"
#include "bvh4.cuh"

extern "C" __global__ void bvh4_while_while(const float4* __restrict__ nodes,
                                            const float4* __restrict__ woop,
                                            const int* __restrict__ tri_index, int root,
                                            const float4* __restrict__ ray_o,
                                            const float4* __restrict__ ray_d, int num_rays,
                                            int any_hit, int* __restrict__ hit_tri,
                                            float* __restrict__ hit_t)
{
    // @block ray_setup
    const int ray = blockIdx.x * blockDim.x + threadIdx.x;
    if (ray >= num_rays) return;
    const Ray r = simt_load_ray(ray_o, ray_d, ray);
    const Bvh4Planes planes = simt_bvh4_planes(nodes, r);
    int stack[SIMT_BVH4_STACK_SIZE];
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
            const Bvh4Hit h = simt_bvh4_intersect_node(nodes, node, r, planes, t_best);
            const int k = simt_bvh4_count(h);
            if (k >= 2) {
                // @block trav_both
                node = simt_bvh4_order_push(h, k, stack, sp);
                // @block trav_step
            } else {
                // @block trav_else
                if (k == 1) {
                    // @block trav_one
                    node = simt_bvh4_single(h);
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
                    // @block tri_test
                }
            }
            // @block leaf_entry
        }
        // @block loop_control
    }
    // @block finish
    simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
    // @end
}
