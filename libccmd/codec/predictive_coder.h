#pragma once

// The entropy stage of ccmd-bounded: an image of integer codes (0 = invalid pixel,
// 1..max_code = a quantiser grid point) is predicted from its causal neighbours with the
// median edge detector of LOCO-I / JPEG-LS (left a, up b, up-left c) and the residuals
// are coded with tANS (tans.h) in 32 contexts: the local activity |a - c| + |b - c| +
// |d - b| (d up-right) in classes of its bit length, for each combination of "left valid"
// and "up valid". Invalid pixels are one more symbol of the same alphabet, so holes cost
// almost nothing and no separate mask is sent; an invalid pixel is "filled" with its
// prediction for its neighbours' sake.
//
// The encoder may be given, per pixel, an interval of acceptable codes instead of one code
// (every depth within the error bound); it then picks the code its own prediction is
// closest to, so that smooth surfaces cost zero residuals as long as the prediction stays
// within the bound. This is near-lossless coding with the quantisation inside the
// prediction loop, as in JPEG-LS, but with a bound relative to depth.
//
// Residual symbols: the zigzagged residual m is coded directly below 16; above, as its bit
// length and the bit after the leading one, followed by the remaining bits raw.
//
// Each row is coded as two halves interleaved pixel by pixel, so that the decoder follows
// two independent dependency chains (one per tANS state) at once.

#include <cstdint>
#include <span>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

// first/last: per pixel (width * height, row-major) the acceptable codes [first, last];
// first = last = 0 for an invalid pixel, first >= 1 otherwise. chosen (optional, width *
// height) gets the codes picked, which DecodePredictive reproduces.
void EncodePredictive(const std::uint16_t* first, const std::uint16_t* last, int width, int height,
                      std::vector<std::uint8_t>* out, std::uint16_t* chosen = nullptr);

// Decodes into codes (width * height values). Fails with kCorrupt on malformed input or on
// a decoded code above max_code. *consumed (optional) gets the bytes used.
Status DecodePredictive(std::span<const std::uint8_t> in, int width, int height, int max_code,
                        std::uint16_t* codes, std::size_t* consumed = nullptr);

}  // namespace ccmd
