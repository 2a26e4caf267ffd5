// Test input of tests/test_kernels_ir.py: warp intrinsics in a divergent loop. On sm_75
// nvcc compiles each `_sync` intrinsic to a converged fast path plus a BRA.DIV stub that
// calls a $__internal_* subroutine. tiny_vote.sm_75.sass is its listing, made with
//   nvcc -arch=sm_75 -cubin -O3 -lineinfo -o tiny_vote.cubin tiny_vote.cu
//   nvdisasm -c -g -gi tiny_vote.cubin > tiny_vote.sm_75.sass  (paths cut to names)
extern "C" __global__ void tiny_vote(const int* __restrict__ a, int* __restrict__ b, int n)
{
    // @block pool_fetch
    int base = 0;
    if ((threadIdx.x & 31) == 0) base = atomicAdd(b, 32);
    base = __shfl_sync(0xffffffffu, base, 0);
    // @block trav_step
    int i = base + (int)threadIdx.x;
#pragma unroll 1
    while (i < n) {
        i += __ldg(a + i);
        if (!__any_sync(__activemask(), i < n - 4)) break;
    }
    // @block finish
    b[threadIdx.x + 1] = i;
    // @end
}
