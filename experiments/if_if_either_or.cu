// if-if read as the seed lecture describes the paper's kernel: "each loop iteration either
// executes a traversal step or a primitive intersection". The loop of if_if.cu
// (kernels_ir/cuda), whose lane may step onto a leaf, enter it and test its first triangle
// in one iteration, with the leaf entry and the test moved into the traversal step's
// `else`: a lane that stepped waits for the next iteration. Not a kernel of the package:
// experiments/if_if_either_or.py compiles it beside kernels_ir/cuda/common.cuh to price
// that reading with its own code.
#include "common.cuh"

extern "C" __global__ void if_if_either_or(const float4* __restrict__ nodes,
                                           const float4* __restrict__ woop,
                                           const int* __restrict__ tri_index, int root,
                                           const float4* __restrict__ ray_o,
                                           const float4* __restrict__ ray_d, int num_rays, int any_hit,
                                           int* __restrict__ hit_tri, float* __restrict__ hit_t)
{
    // @block ray_setup
    const int ray = blockIdx.x * blockDim.x + threadIdx.x;
    if (ray >= num_rays) return;
    const Ray r = simt_load_ray(ray_o, ray_d, ray);
    int stack[SIMT_STACK_SIZE];
    int sp = 0;
    stack[0] = SIMT_SENTINEL;
    int node = root;
    int tri = -1;  // float4 index of the next untested triangle of the current leaf
    float4 w0 = make_float4(0.0f, 0.0f, 0.0f, 0.0f);  // its first float4
    int hit_addr = -1;
    float t_best = r.tmax;
    // @block loop_control
#pragma unroll 1
    while (node != SIMT_SENTINEL || tri >= 0) {
        // @block trav_step
        if (tri < 0 && simt_is_interior(node)) {
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
        } else {
            // @block leaf_entry
            if (tri < 0) {  // at a leaf: enter it (pop the next node)
                tri = ~node;
                w0 = __ldg(woop + tri);
                node = stack[sp--];
                if (simt_is_tri_end(w0)) tri = -1;  // empty leaf
            }
            // @block tri_test
            if (tri >= 0) {
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
                    if (simt_opaque(any_hit)) break;
                }
                // @block tri_test
                tri += 3;
                w0 = __ldg(woop + tri);
                if (simt_is_tri_end(w0)) tri = -1;
            }
        }
        // @block loop_control
    }
    // @block finish
    simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
    // @end
}
