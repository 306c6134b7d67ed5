#pragma once

// Fast static Huffman coding of a byte sequence, for ccmd-lossless: canonical codes
// limited to 11 bits, built from the sequence's own histogram, and four independent bit
// streams (the sequence's four quarters) that the decoder walks in lockstep, so that four
// dependency chains overlap. Decoding a byte is one lookup in a 2048-entry table.
//
// Stream:
//   varint  number of bytes coded (n)
//   u8      largest byte value present (m); absent when n = 0
//   (m + 2) / 2 bytes: code length of each value 0..m, 4 bits each, low nibble first
//   3 x varint  sizes of streams 0..2 in bytes (stream 3 takes the rest)
//   streams 0..3, bits least significant first
// A sequence of one distinct value has no bits at all.
//
// Decoding checks every length against the input and the caller's limit before
// allocating, never reads out of bounds (the streams are copied with zero padding), and
// verifies at the end that each stream was used exactly.

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

constexpr int kHuffmanMaxBits = 11;

// Appends the coded bytes to *out.
void HuffmanEncode(std::span<const std::uint8_t> in, std::vector<std::uint8_t>* out);

// Decodes into *out (replacing it); a count above max_output is rejected (kOutOfRange)
// before allocating. *consumed (optional) gets the bytes of `in` used.
Status HuffmanDecode(std::span<const std::uint8_t> in, std::size_t max_output,
                     std::vector<std::uint8_t>* out, std::size_t* consumed = nullptr);

// The same for an image of residual bytes (0 = invalid pixel, 1 = exact prediction, small
// values = small residuals), with a context per pixel: the classes (invalid, exact, small,
// large) of the byte above and the byte to the left select one of 16 code tables. The
// four streams are bands of whole rows, so both neighbours are decoded before they are
// needed; a band's first row and each row's first pixel see the class "invalid".
//   per context: u8 largest value present (m), then (m + 2) / 2 bytes of 4-bit lengths;
//                all lengths zero means the context holds only the value m (no bits)
//   3 x varint   sizes of streams 0..2 in bytes (stream 3 takes the rest)
//   streams 0..3
void HuffmanEncodeImage(std::span<const std::uint8_t> in, int width, int height,
                        std::vector<std::uint8_t>* out);
Status HuffmanDecodeImage(std::span<const std::uint8_t> in, int width, int height,
                          std::vector<std::uint8_t>* out, std::size_t* consumed = nullptr);

// Code lengths (0 = unused) for a histogram, limited to max_bits; exposed for tests.
std::vector<int> HuffmanCodeLengths(const std::uint32_t* counts, int alphabet, int max_bits);

}  // namespace ccmd
