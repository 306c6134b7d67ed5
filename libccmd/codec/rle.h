#pragma once

// Run-length coding of 16-bit samples (the paper's eq. 5: each run as value and count),
// with literal groups so that a noisy stretch does not double in size. The stream is a
// sequence of tokens, each a varint t followed by samples (u16 little-endian):
//   t even: literal group, (t >> 1) + 1 samples follow
//   t odd:  run, one sample follows, repeated (t >> 1) + 1 times
// Runs start at 3 equal samples (a run of 2 would cost as much as two literals).

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

// Appends the coded samples to *out.
void RleEncode(std::span<const std::uint16_t> samples, std::vector<std::uint8_t>* out);

// Decodes exactly `num_samples` samples (the caller knows the image size). Fails with
// kCorrupt on truncation, on runs or groups that overshoot num_samples and on trailing
// bytes; never writes past num_samples.
Status RleDecode(std::span<const std::uint8_t> in, std::size_t num_samples,
                 std::vector<std::uint16_t>* out);

}  // namespace ccmd
