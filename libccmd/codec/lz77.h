#pragma once

// An in-tree LZ77 byte coder (Ziv and Lempel, 1977) built for fast decoding: byte-aligned
// sequences of literals and back-references, no entropy stage. Stream layout:
//   varint  raw_size
//   then sequences until raw_size bytes are produced:
//     u8      token: high nibble literal count L, low nibble match length M - 4
//     [u8..]  if L == 15: more literal count, bytes added while each is 255
//     L bytes literals
//     (the stream may end here when raw_size is reached)
//     u16     match offset, 1..65535, at most the bytes produced so far
//     [u8..]  if M - 4 == 15: more match length, as for literals
// Matches are at least 4 bytes and may overlap their own output (offset < length repeats a
// pattern, which is how runs are coded).

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

struct Lz77Options {
  // Candidates examined per position in the hash chain: 1 is fastest; 16-64 finds longer
  // matches at a few times the encoding time. Decoding speed does not depend on it.
  int max_chain = 8;
};

// Appends the compressed form of `in` to *out.
void Lz77Compress(std::span<const std::uint8_t> in, std::vector<std::uint8_t>* out,
                  const Lz77Options& options = {});

// Decodes a whole stream into *out (replacing its contents). A raw_size above max_output is
// rejected (kOutOfRange) before anything is allocated; every literal count, offset and
// length is checked against the input left and the output produced, so corrupt input gives
// kCorrupt and never reads or writes out of bounds.
Status Lz77Decompress(std::span<const std::uint8_t> in, std::size_t max_output,
                      std::vector<std::uint8_t>* out);

}  // namespace ccmd
