// Wavefront path tracing, stage 4 of 4: trace the connect queue's shadow rays (any hit)
// with while-while traversal and add the light of each unoccluded one to its path.
// A path has at most one shadow ray per bounce, so the read-modify-write of radiance
// needs no atomic.
// Queue: c_o/c_d (ray layout of common.cuh), c_path, c_contrib = (r, g, b, 0) carried if
// unoccluded, *c_count = length.
// Launch: any grid covering the queue's capacity.
#include "common.cuh"

extern "C" __global__ void wavefront_connect(const float4* __restrict__ nodes,
                                             const float4* __restrict__ woop, int root,
                                             const float4* __restrict__ c_o,
                                             const float4* __restrict__ c_d,
                                             const int* __restrict__ c_path,
                                             const float4* __restrict__ c_contrib,
                                             const int* __restrict__ c_count,
                                             float4* __restrict__ radiance)
{
    // @block ray_setup
    const int entry = blockIdx.x * blockDim.x + threadIdx.x;
    if (entry >= *c_count) return;
    const Ray r = simt_load_ray(c_o, c_d, entry);
    int stack[SIMT_STACK_SIZE];
    int sp = 0;
    stack[0] = SIMT_SENTINEL;
    int node = root;
    bool occluded = false;
    // @block loop_control
#pragma unroll 1
    while (node != SIMT_SENTINEL) {
        // @block trav_step
#pragma unroll 1
        while (simt_is_interior(node)) {
            const NodeHit h = simt_intersect_node(nodes, node, r, r.tmax);
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
                bool hit = simt_woop_t(w0, r, r.tmax, &s);
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
                // @block tri_hit
                if (hit) {
                    occluded = true;
                    node = SIMT_SENTINEL;
                    break;
                }
                // @block tri_test
            }
            // @block leaf_entry
        }
        // @block loop_control
    }
    // @block finish
    if (!occluded) {
        const int path = __ldg(c_path + entry);
        const float4 c = __ldg(c_contrib + entry);
        const float4 acc = radiance[path];
        radiance[path] = make_float4(acc.x + c.x, acc.y + c.y, acc.z + c.z, acc.w);
    }
    // @end
}
