#version 430
// viewer/gl_sort.py, the two one-invocation steps around the cull pass (sort_depth.comp).
// RESET 1: empty statistics before the cull pass accumulates into them.
// RESET 0: after it, the key scale 65534 / (zmax - zmin) of the visible depths (for
// sort_keys.comp, so the host never reads the range) and the indexed indirect draw command
// (count = visible Gaussians), so the draw needs no readback either.
layout(local_size_x = 1) in;

// visible count, zmin, zmax (as order-preserving uints, see sort_depth.comp), key scale (float bits)
layout(std430, binding = 0) buffer Stats { uint stats[4]; };

#if !RESET
// glDrawElementsIndirect: count, instanceCount, firstIndex, baseVertex, baseInstance
layout(std430, binding = 1) writeonly buffer Command { uint command[5]; };

float from_ordered(uint bits) {
    return uintBitsToFloat((bits & 0x80000000u) != 0u ? bits & 0x7FFFFFFFu : ~bits);
}
#endif

void main() {
#if RESET
    stats[0] = 0u;
    stats[1] = 0xFFFFFFFFu;
    stats[2] = 0u;
    stats[3] = 0u;
#else
    uint visible = stats[0];
    float zmin = from_ordered(stats[1]), zmax = from_ordered(stats[2]);
    // float32 division: torch divides in float64 and rounds to float32, so this scale can be
    // one ulp away from torch's, and a key at a floor boundary one level away (documented)
    float scale = (visible > 0u && zmax > zmin) ? 65534.0 / (zmax - zmin) : 0.0;
    stats[3] = floatBitsToUint(scale);
    command[0] = visible;
    command[1] = 1u;
    command[2] = 0u;
    command[3] = 0u;
    command[4] = 0u;
#endif
}
