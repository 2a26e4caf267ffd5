// Test input of tests/test_kernels_ir.py: a tiny kernel with block markers, an inlined
// header helper and a loop. tiny.sm_90.sass is its listing, made with
//   nvcc -arch=sm_90 -cubin -O3 -lineinfo -o tiny.cubin tiny.cu
//   nvdisasm -c -g -gi tiny.cubin > tiny.sm_90.sass  (sm_100 alike; paths cut to names)
#include "tiny.cuh"

extern "C" __global__ void tiny(const float* __restrict__ a, float* __restrict__ b, int n)
{
    // @block ray_setup
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    float s = 0.0f;
    // @block trav_step
#pragma unroll 1
    for (int j = 0; j < n; ++j) {
        s += tiny_weight(a, j * i);
    }
    // @block finish
    b[i] = s;
    // @end
}
