// Inlined helper of tiny.cu: its SASS must be charged to the line that calls it.
__device__ __forceinline__ float tiny_weight(const float* __restrict__ p, int i)
{
    const float v = __ldg(p + i);
    const float w = __ldg(p + i + 7);
    return v * w + w;
}
