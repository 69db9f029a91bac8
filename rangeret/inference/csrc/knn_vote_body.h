/* The vote over points start..stop (see knn_vote.c), included once per instruction set with
 * TARGET, LANES, VF, VI, GATHER_PS, GATHER_EPI32 and KERNEL defined (see knn_vote.c), which it
 * undefines again. */
static TARGET int32_t KERNEL(
    const float *far, const int32_t *codes, int32_t height, int32_t width, int32_t pad,
    const int32_t *offsets, const float *weights, int32_t size, const float *ranges,
    const int64_t *proj_x, const int64_t *proj_y, int64_t start, int64_t stop, int32_t wanted,
    int32_t use_cutoff, float cutoff, int32_t num_classes, int32_t votes_from, int64_t *out)
{
    const int32_t stride = width + 2 * pad;
    const int32_t slots = wanted < size ? wanted : size;
    const int32_t base = num_classes + 2;
    const int32_t origin = pad * stride + pad;
    /* the kept neighbours' distances (as bits) and codes, nearest first; a placeholder is NaN,
     * which no distance is >= to, so a neighbour always goes before it */
    VI kept[MAX_SLOTS], kept_codes[MAX_SLOTS];
    VI voters[MAX_SLOTS + 1];
    for (int64_t first = start; first < stop; first += LANES) {
        const int32_t lanes = stop - first < LANES ? (int32_t)(stop - first) : LANES;
        VI column;
        VF near;
        for (int32_t l = 0; l < LANES; ++l) {
            const int64_t p = first + (l < lanes ? l : 0); /* spare lanes repeat the first point */
            const int64_t x = proj_x[p], y = proj_y[p];
            if (x >= width || (x >= 0 && (y < 0 || y >= height))) return -3;
            column[l] = x < 0 ? origin : (int32_t)y * stride + (int32_t)x + origin;
            near[l] = ranges[p];
        }
        for (int32_t i = 0; i < slots; ++i) {
            kept[i] = (VI){0} + 0x7fc00000;
            kept_codes[i] = (VI){0};
        }
        for (int32_t j = 0; j < size; ++j) {
            const VI at = column + offsets[j];
            VF dist = GATHER_PS(far, at) - near;
            dist = (VF)((VI)dist & 0x7fffffff) * weights[j]; /* |difference| times the weight */
            const VI code = GATHER_EPI32(codes, at);
            const VI bits = (VI)dist;
            /* insertion: slot i keeps its entry where it is <= dist, takes the new entry where
             * slot i - 1 kept its own, and slot i - 1's entry otherwise */
            VI before = (VI)((VF)kept[0] <= dist);
            VI moved = kept[0], moved_code = kept_codes[0];
            kept[0] = PICK(before, kept[0], bits);
            kept_codes[0] = PICK(before, kept_codes[0], code);
            for (int32_t i = 1; i < slots; ++i) {
                const VI stays = (VI)((VF)kept[i] <= dist);
                const VI down = PICK(before, bits, moved);
                const VI down_code = PICK(before, code, moved_code);
                moved = kept[i];
                moved_code = kept_codes[i];
                kept[i] = PICK(stays, kept[i], down);
                kept_codes[i] = PICK(stays, kept_codes[i], down_code);
                before = stays;
            }
        }
        int32_t count = 0;
        voters[count++] = GATHER_EPI32(codes, column);
        for (int32_t i = 0; i < slots; ++i)
            voters[count++] = use_cutoff ? PICK((VI)((VF)kept[i] <= cutoff), kept_codes[i], (VI){0})
                                         : kept_codes[i];
        VI best = (VI){0};
        for (int32_t i = 0; i < count; ++i) {
            VI same = (VI){0};
            for (int32_t m = 0; m < count; ++m) same -= (VI)(voters[m] == voters[i]);
            const VI score = PICK((VI)(voters[i] != 0), same * base + voters[i], (VI){0});
            best = PICK((VI)(score > best), score, best);
        }
        for (int32_t l = 0; l < lanes; ++l)
            if (proj_x[first + l] >= 0)
                out[first + l] = best[l] ? num_classes + 1 - best[l] % base : votes_from;
    }
    return 0;
}

#undef TARGET
#undef LANES
#undef VF
#undef VI
#undef GATHER_PS
#undef GATHER_EPI32
#undef KERNEL
