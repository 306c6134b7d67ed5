#include "libccmd/codec/lz77.h"

#include <algorithm>
#include <cstring>
#include <string>

#include "proto/byte_io.h"

namespace ccmd {
namespace {

constexpr int kHashBits = 15;
constexpr std::size_t kMinMatch = 4;
constexpr std::size_t kMaxOffset = 65535;
constexpr std::size_t kWindowMask = 0xFFFF;
// The last bytes of the input are always literals; keeps the match finder's 4-byte loads
// inside the input.
constexpr std::size_t kTailLiterals = 8;
// Output slack for the decoder's 8-byte match copies.
constexpr std::size_t kCopySlack = 16;

std::uint32_t Load32(const std::uint8_t* p) {
  std::uint32_t v;
  std::memcpy(&v, p, 4);
  return v;
}

std::uint32_t Hash4(std::uint32_t v) { return (v * 2654435761u) >> (32 - kHashBits); }

void PutLengthTail(std::size_t extra, std::vector<std::uint8_t>* out) {
  while (extra >= 255) {
    out->push_back(255);
    extra -= 255;
  }
  out->push_back(static_cast<std::uint8_t>(extra));
}

// Literals [lit, lit + lit_len), then (if match_len > 0) a match.
void EmitSequence(const std::uint8_t* lit, std::size_t lit_len, std::size_t offset,
                  std::size_t match_len, std::vector<std::uint8_t>* out) {
  const std::size_t lit_code = std::min<std::size_t>(lit_len, 15);
  const std::size_t match_code = match_len ? std::min<std::size_t>(match_len - kMinMatch, 15) : 0;
  out->push_back(static_cast<std::uint8_t>((lit_code << 4) | match_code));
  if (lit_code == 15) PutLengthTail(lit_len - 15, out);
  if (lit_len > 0) {
    const std::size_t at = out->size();
    out->resize(at + lit_len);
    std::memcpy(out->data() + at, lit, lit_len);
  }
  if (match_len == 0) return;
  out->push_back(static_cast<std::uint8_t>(offset));
  out->push_back(static_cast<std::uint8_t>(offset >> 8));
  if (match_code == 15) PutLengthTail(match_len - kMinMatch - 15, out);
}

}  // namespace

void Lz77Compress(std::span<const std::uint8_t> in, std::vector<std::uint8_t>* out,
                  const Lz77Options& options) {
  const std::size_t n = in.size();
  std::uint64_t size = n;
  while (size >= 0x80) {
    out->push_back(static_cast<std::uint8_t>(size | 0x80));
    size >>= 7;
  }
  out->push_back(static_cast<std::uint8_t>(size));
  if (n == 0) return;
  const std::uint8_t* src = in.data();
  std::size_t anchor = 0;
  if (n >= kMinMatch + kTailLiterals) {
    const int max_chain = std::max(1, options.max_chain);
    std::vector<std::int32_t> head(std::size_t{1} << kHashBits, -1);
    std::vector<std::int32_t> prev(max_chain > 1 ? kWindowMask + 1 : 0, -1);
    auto insert = [&](std::size_t pos) {
      const std::uint32_t h = Hash4(Load32(src + pos));
      if (max_chain > 1) prev[pos & kWindowMask] = head[h];
      head[h] = static_cast<std::int32_t>(pos);
    };
    const std::size_t match_end = n - kTailLiterals;  // matches end at or before this
    std::size_t i = 0;
    while (i + kMinMatch <= match_end) {
      const std::uint32_t v = Load32(src + i);
      std::int64_t candidate = head[Hash4(v)];
      std::size_t best_len = 0, best_offset = 0;
      for (int step = 0; step < max_chain && candidate >= 0; ++step) {
        const std::size_t c = static_cast<std::size_t>(candidate);
        if (i - c > kMaxOffset) break;
        if (Load32(src + c) == v) {
          std::size_t len = kMinMatch;
          while (i + len < match_end && src[c + len] == src[i + len]) ++len;
          if (len > best_len) {
            best_len = len;
            best_offset = i - c;
          }
        }
        if (max_chain == 1) break;
        const std::int64_t next = prev[c & kWindowMask];
        if (next >= candidate) break;  // stale entry from a position beyond the window
        candidate = next;
      }
      insert(i);
      if (best_len >= kMinMatch) {
        EmitSequence(src + anchor, i - anchor, best_offset, best_len, out);
        for (std::size_t k = i + 1; k < i + best_len && k + kMinMatch <= n; ++k) insert(k);
        i += best_len;
        anchor = i;
      } else {
        // Skip faster through data that does not match (random bytes).
        i += 1 + ((i - anchor) >> 7);
      }
    }
  }
  EmitSequence(src + anchor, n - anchor, 0, 0, out);
}

Status Lz77Decompress(std::span<const std::uint8_t> in, std::size_t max_output,
                      std::vector<std::uint8_t>* out) {
  ByteReader header(in);
  std::uint64_t raw_size;
  CCMD_RETURN_IF_ERROR(header.ReadVarint(&raw_size));
  if (raw_size > max_output) {
    return OutOfRange("LZ77 stream claims " + std::to_string(raw_size) +
                      " bytes, more than the limit of " + std::to_string(max_output));
  }
  // Each input byte yields at most 255 output bytes (a length-extension byte), so a claim
  // beyond that is corrupt; checked before allocating.
  if (raw_size > 255 * static_cast<std::uint64_t>(in.size()) + 64) {
    return Corrupt("LZ77 stream claims " + std::to_string(raw_size) + " bytes from only " +
                   std::to_string(in.size()) + " input bytes");
  }
  out->resize(raw_size + kCopySlack);
  std::uint8_t* dst = out->data();
  const std::uint8_t* ip = in.data() + header.position();
  const std::uint8_t* const iend = in.data() + in.size();
  std::size_t op = 0;
  auto fail = [&](const char* what) {
    out->clear();
    return Corrupt(std::string("LZ77: ") + what + " at input offset " +
                   std::to_string(ip - in.data()));
  };
  while (op < raw_size) {
    if (ip >= iend) return fail("truncated before a token");
    const std::uint8_t token = *ip++;
    std::size_t lit = token >> 4;
    if (lit == 15) {
      std::uint8_t b;
      do {
        if (ip >= iend) return fail("truncated literal length");
        b = *ip++;
        lit += b;
        if (lit > raw_size) return fail("literal length beyond the output size");
      } while (b == 255);
    }
    if (lit > static_cast<std::size_t>(iend - ip)) return fail("truncated literals");
    if (lit > raw_size - op) return fail("literals overshoot the output size");
    std::memcpy(dst + op, ip, lit);
    ip += lit;
    op += lit;
    if (op == raw_size) break;
    if (iend - ip < 2) return fail("truncated match offset");
    const std::size_t offset = ip[0] | (static_cast<std::size_t>(ip[1]) << 8);
    ip += 2;
    if (offset == 0 || offset > op) return fail("match offset outside the output");
    std::size_t len = (token & 15) + kMinMatch;
    if ((token & 15) == 15) {
      std::uint8_t b;
      do {
        if (ip >= iend) return fail("truncated match length");
        b = *ip++;
        len += b;
        if (len > raw_size) return fail("match length beyond the output size");
      } while (b == 255);
    }
    if (len > raw_size - op) return fail("match overshoots the output size");
    std::uint8_t* d = dst + op;
    const std::uint8_t* s = d - offset;
    if (offset >= 8) {
      // 8-byte steps may write up to 7 bytes past the match, into the slack; every chunk
      // read lies before the chunk being written, so overlap is safe.
      for (std::size_t k = 0; k < len; k += 8) std::memcpy(d + k, s + k, 8);
    } else if (offset == 1) {
      std::memset(d, *s, len);
    } else {
      for (std::size_t k = 0; k < len; ++k) d[k] = s[k];
    }
    op += len;
  }
  if (ip != iend) return fail("trailing bytes after the stream");
  out->resize(raw_size);
  return Status::Ok();
}

}  // namespace ccmd
