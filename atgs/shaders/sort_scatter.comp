#version 430
// viewer/gl_sort.py, radix pass step 3 of 3: each block's items go, in their order, to the
// slots the scanned counts give their digit in that block: stable by construction, since
// one invocation walks its block sequentially and blocks own disjoint, ordered slot ranges.
// INPUT_PAIRS as in sort_histogram.comp; OUTPUT_PAIRS 1: write (key, index) pairs for the
// next pass; 0: write only the index (the last pass, into the element buffer).
layout(local_size_x = 64) in;

#if INPUT_PAIRS
layout(std430, binding = 0) readonly buffer Items { uvec2 items[]; };
#else
layout(std430, binding = 0) readonly buffer Keys { uint keys[]; };
#endif
layout(std430, binding = 1) readonly buffer Offsets { uint offsets[]; };  // scanned counts
#if OUTPUT_PAIRS
layout(std430, binding = 2) writeonly buffer Sorted { uvec2 sorted_items[]; };
#else
layout(std430, binding = 2) writeonly buffer Sorted { uint sorted_index[]; };
#endif

uniform uint u_count;
uniform uint u_blocks;
uniform uint u_shift;

// This invocation's item: dispatches wider than 65535 groups are split over y (gl_sort._run).
uint item_index() {
    return (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x + gl_LocalInvocationID.x;
}

void main() {
    uint b = item_index();
    if (b < u_blocks) {
        uint next[256];  // the next free slot of each digit
        for (uint d = 0u; d < 256u; ++d) {
            next[d] = offsets[d * u_blocks + b];
        }
        uint end = min(u_count, (b + 1u) * BLOCK_SIZE);
        for (uint i = b * BLOCK_SIZE; i < end; ++i) {
#if INPUT_PAIRS
            uvec2 item = items[i];
#else
            uvec2 item = uvec2(keys[i], i);
#endif
            uint digit = (item.x >> u_shift) & 255u;
            uint slot = next[digit];
            next[digit] = slot + 1u;
#if OUTPUT_PAIRS
            sorted_items[slot] = item;
#else
            sorted_index[slot] = item.y;
#endif
        }
    }
}
