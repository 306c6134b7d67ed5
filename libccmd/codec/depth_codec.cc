#include "libccmd/codec/depth_codec.h"

#include <algorithm>
#include <cstring>

#include "libccmd/codec/depth_lossless.h"
#include "libccmd/codec/depth_quantizer.h"
#include "libccmd/codec/huffman.h"
#include "libccmd/codec/lz77.h"
#include "libccmd/codec/predictive_coder.h"
#include "libccmd/codec/residual_bytes.h"
#include "libccmd/codec/rle.h"
#include "proto/byte_io.h"

namespace ccmd {
namespace {

constexpr std::uint8_t kMagic = 0xD7;
constexpr std::uint8_t kVersion = 1;

struct ModeInfo {
  DepthMode mode;
  const char* name;
  bool lossless;
};

constexpr ModeInfo kModes[kNumDepthModes] = {
    {DepthMode::kRaw, "ds", true},
    {DepthMode::kRle, "ds+rle", true},
    {DepthMode::kRleLz77, "ds+rle+lz77", true},
    {DepthMode::kEq6Rle, "ds+qt+rle", false},
    {DepthMode::kEq6RleLz77, "ds+qt+rle+lz77", false},
    {DepthMode::kLossless, "ccmd-lossless", true},
    {DepthMode::kQuantised, "ccmd-quantised", false},
    {DepthMode::kBounded, "ccmd-bounded", false},
};

// Modes whose samples are eq. 6 codes run through the paper's stages.
bool UsesEq6(DepthMode mode) {
  return mode == DepthMode::kEq6Rle || mode == DepthMode::kEq6RleLz77;
}

// ccmd-quantised: the paper's pipeline (eq. 6 quantiser, run-length, LZ77) made to compete.
// The quantiser codes are first turned into prediction residuals, one byte per pixel
// (residual_bytes.h); LZ77 then codes the runs (its overlapping matches with offset 1 are
// run-length codes; a separate run-length stage in front measured 16 % larger on real
// frames, so there is none) and the repetitions, and a Huffman stage codes LZ77's output.
//   varint escape stream size, escape stream, Huffman(LZ77(residual bytes))
void EncodeQuantised(std::span<const std::uint16_t> depth, int width, int height,
                     const Lz77Options& lz, std::vector<std::uint8_t>* out) {
  const std::size_t n = depth.size();
  std::vector<std::uint8_t> bytes(n);
  ByteWriter escapes;
  CodesToResidualBytes(
      width, height,
      [&](int x, int y) {
        return static_cast<int>(QuantizeEq6(depth[static_cast<std::size_t>(y) * width + x]));
      },
      bytes.data(), &escapes);
  ByteWriter w;
  w.PutVarint(escapes.size());
  w.PutBytes(escapes.bytes());
  out->insert(out->end(), w.data(), w.data() + w.size());
  std::vector<std::uint8_t> packed;
  Lz77Compress(bytes, &packed, lz);
  HuffmanEncode(packed, out);
}

Status DecodeQuantised(std::span<const std::uint8_t> in, int width, int height,
                       std::uint16_t* depth) {
  // Code -> bin centre, padded to a power of two for masked indexing.
  static const std::vector<std::uint16_t> dequantise = [] {
    std::vector<std::uint16_t> t(8192, 0);
    for (int c = 0; c <= kEq6MaxCode; ++c) t[c] = DequantizeEq6(static_cast<std::uint16_t>(c));
    return t;
  }();
  const std::size_t n = static_cast<std::size_t>(width) * height;
  ByteReader r(in);
  std::uint64_t escape_size;
  CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(r.remaining(), &escape_size, "escape stream size"));
  std::span<const std::uint8_t> escape_bytes;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(escape_size, &escape_bytes));
  ByteReader escapes(escape_bytes);
  std::vector<std::uint8_t> packed, bytes;
  std::size_t used = 0;
  // LZ77 never grows its input by more than a length byte per 255 literals and a token.
  CCMD_RETURN_IF_ERROR(HuffmanDecode(in.subspan(r.position()), n + n / 64 + 64, &packed, &used));
  if (r.position() + used != in.size()) return Corrupt("trailing bytes after the depth data");
  CCMD_RETURN_IF_ERROR(Lz77Decompress(packed, n, &bytes));
  if (bytes.size() != n) return Corrupt("quantised depth: wrong number of pixels");
  return ResidualBytesToValues(bytes.data(), width, height, &escapes, kEq6MaxCode,
                               dequantise.data(), 8191, depth);
}

std::span<const std::uint16_t> Samples(const cv::Mat& m) {
  return {m.ptr<std::uint16_t>(0), m.total()};
}

}  // namespace

const char* DepthModeName(DepthMode mode) {
  const int i = static_cast<int>(mode);
  return i >= 0 && i < kNumDepthModes ? kModes[i].name : "?";
}

StatusOr<DepthMode> ParseDepthMode(std::string_view name) {
  for (const ModeInfo& m : kModes) {
    if (name == m.name) return m.mode;
  }
  return InvalidArgument("unknown depth mode '" + std::string(name) + "'");
}

bool DepthModeIsLossless(DepthMode mode) {
  const int i = static_cast<int>(mode);
  return i >= 0 && i < kNumDepthModes && kModes[i].lossless;
}

Status DepthEncodeOptions::Validate() const {
  if (static_cast<int>(mode) >= kNumDepthModes) return InvalidArgument("unknown depth mode");
  if (downsample != 1 && downsample != 2 && downsample != 4) {
    return InvalidArgument("downsample must be 1, 2 or 4");
  }
  if (bound_e4 < 1 || bound_e4 > 2000) {
    return InvalidArgument("bound_e4 must be in 1..2000 (0.01 % .. 20 %)");
  }
  if (lz77_chain < 1 || lz77_chain > 4096) return InvalidArgument("lz77_chain must be in 1..4096");
  return Status::Ok();
}

void DepthEncodeOptions::Describe(OptionsWriter* out) const {
  out->Add("mode", DepthModeName(mode));
  out->Add("downsample", downsample);
  out->Add("downsample_method", DownsampleMethodName(downsample_method));
  out->Add("bound_e4", bound_e4);
  out->Add("lz77_chain", lz77_chain);
}

Status DepthDecodeOptions::Validate() const {
  if (max_pixels == 0) return InvalidArgument("max_pixels must be positive");
  return Status::Ok();
}

void DepthDecodeOptions::Describe(OptionsWriter* out) const { out->Add("max_pixels", max_pixels); }

double DepthModeErrorBound(DepthMode mode, int bound_e4, std::uint16_t depth_mm) {
  if (DepthModeIsLossless(mode)) return 0.0;
  if (mode == DepthMode::kBounded) return bound_e4 * 1e-4 * depth_mm;
  // Bins of 1, 2, 4, 8 mm from 0.2, 3, 6, 12 m on, decoded to their centre.
  if (depth_mm < 3000) return 0.0;
  if (depth_mm < 6000) return 1.0;
  if (depth_mm < 12000) return 2.0;
  return 4.0;
}

StatusOr<std::vector<std::uint8_t>> EncodeDepth(const cv::Mat& depth_mm,
                                                const DepthEncodeOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  if (depth_mm.type() != CV_16UC1) return InvalidArgument("depth must be CV_16UC1 millimetres");
  if (depth_mm.empty()) return InvalidArgument("empty depth image");
  cv::Mat image = depth_mm;  // at r = 1 the input itself, not a copy
  if (options.downsample != 1) {
    CCMD_ASSIGN_OR_RETURN(image,
                          DownsampleDepth(depth_mm, options.downsample, options.downsample_method));
  }
  if (!image.isContinuous()) image = image.clone();
  if (image.cols > 65535 || image.rows > 65535 || image.empty()) {
    return InvalidArgument("depth image size not codable");
  }
  const DepthMode mode = options.mode;
  ByteWriter w(image.total() / 2 + 64);
  w.PutU8(kMagic);
  w.PutU8(kVersion);
  w.PutU8(static_cast<std::uint8_t>(mode));
  w.PutU8(static_cast<std::uint8_t>(options.downsample));
  w.PutU16(static_cast<std::uint16_t>(image.cols));
  w.PutU16(static_cast<std::uint16_t>(image.rows));
  w.PutU16(static_cast<std::uint16_t>(mode == DepthMode::kBounded ? options.bound_e4 : 0));
  std::vector<std::uint8_t>& out = w.buffer();
  const std::size_t n = image.total();

  std::vector<std::uint16_t> codes;
  std::span<const std::uint16_t> samples = Samples(image);
  if (UsesEq6(mode)) {
    codes.resize(n);
    for (std::size_t i = 0; i < n; ++i) codes[i] = QuantizeEq6(samples[i]);
    samples = codes;
  }
  const Lz77Options lz{options.lz77_chain};
  switch (mode) {
    case DepthMode::kRaw:
      for (std::uint16_t v : samples) w.PutU16(v);
      break;
    case DepthMode::kRle:
    case DepthMode::kEq6Rle:
      RleEncode(samples, &out);
      break;
    case DepthMode::kRleLz77:
    case DepthMode::kEq6RleLz77: {
      std::vector<std::uint8_t> rle;
      RleEncode(samples, &rle);
      Lz77Compress(rle, &out, lz);
      break;
    }
    case DepthMode::kQuantised:
      EncodeQuantised(samples, image.cols, image.rows, lz, &out);
      break;
    case DepthMode::kLossless:
      EncodeDepthLossless(samples.data(), image.cols, image.rows, &out);
      break;
    case DepthMode::kBounded: {
      const RelativeQuantizer& q = RelativeQuantizer::ForBound(options.bound_e4);
      std::vector<std::uint16_t> first(n), last(n);
      for (std::size_t i = 0; i < n; ++i) {
        first[i] = q.FirstAdmissible(samples[i]);
        last[i] = q.LastAdmissible(samples[i]);
      }
      EncodePredictive(first.data(), last.data(), image.cols, image.rows, &out);
      break;
    }
  }
  return w.Take();
}

StatusOr<DepthHeader> ParseDepthHeader(std::span<const std::uint8_t> bytes) {
  ByteReader r(bytes);
  std::uint8_t magic, version, mode, downsample;
  std::uint16_t width, height, bound;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&magic));
  if (magic != kMagic) return Corrupt("not a depth bitstream (bad magic)");
  CCMD_RETURN_IF_ERROR(r.ReadU8(&version));
  if (version != kVersion) {
    return Unsupported("depth bitstream version " + std::to_string(version) +
                       " is not supported (this build reads version 1)");
  }
  CCMD_RETURN_IF_ERROR(r.ReadU8(&mode));
  CCMD_RETURN_IF_ERROR(r.ReadU8(&downsample));
  CCMD_RETURN_IF_ERROR(r.ReadU16(&width));
  CCMD_RETURN_IF_ERROR(r.ReadU16(&height));
  CCMD_RETURN_IF_ERROR(r.ReadU16(&bound));
  if (mode >= kNumDepthModes) return Corrupt("unknown depth mode " + std::to_string(mode));
  if (downsample != 1 && downsample != 2 && downsample != 4) {
    return Corrupt("depth downsample factor " + std::to_string(downsample) + " is not 1, 2, 4");
  }
  if (width == 0 || height == 0) return Corrupt("depth image has zero size");
  const auto m = static_cast<DepthMode>(mode);
  if ((m == DepthMode::kBounded) != (bound != 0) || bound > 2000) {
    return Corrupt("depth error bound " + std::to_string(bound) + " invalid for mode " +
                   DepthModeName(m));
  }
  return DepthHeader{m, downsample, width, height, bound};
}

StatusOr<cv::Mat> DecodeDepth(std::span<const std::uint8_t> bytes,
                              const DepthDecodeOptions& options, DepthHeader* header_out) {
  CCMD_ASSIGN_OR_RETURN(const DepthHeader h, ParseDepthHeader(bytes));
  const std::uint64_t n = static_cast<std::uint64_t>(h.width) * h.height;
  if (n > options.max_pixels) {
    return OutOfRange("depth image " + std::to_string(h.width) + "x" + std::to_string(h.height) +
                      " exceeds the limit of " + std::to_string(options.max_pixels) + " pixels");
  }
  const std::span<const std::uint8_t> payload = bytes.subspan(kDepthHeaderSize);
  cv::Mat image(h.height, h.width, CV_16UC1);
  std::uint16_t* dst = image.ptr<std::uint16_t>(0);
  std::vector<std::uint16_t> samples;
  switch (h.mode) {
    case DepthMode::kRaw: {
      if (payload.size() != 2 * n) return Corrupt("raw depth payload has the wrong size");
      for (std::size_t i = 0; i < n; ++i) dst[i] = payload[2 * i] | (payload[2 * i + 1] << 8);
      break;
    }
    case DepthMode::kRle:
    case DepthMode::kEq6Rle:
      CCMD_RETURN_IF_ERROR(RleDecode(payload, n, &samples));
      break;
    case DepthMode::kRleLz77:
    case DepthMode::kEq6RleLz77: {
      std::vector<std::uint8_t> rle;
      // Run-length data is at most 3 bytes per sample plus token bytes.
      CCMD_RETURN_IF_ERROR(Lz77Decompress(payload, 4 * n + 16, &rle));
      CCMD_RETURN_IF_ERROR(RleDecode(rle, n, &samples));
      break;
    }
    case DepthMode::kQuantised:
      CCMD_RETURN_IF_ERROR(DecodeQuantised(payload, h.width, h.height, dst));
      break;
    case DepthMode::kLossless:
      CCMD_RETURN_IF_ERROR(DecodeDepthLossless(payload, h.width, h.height, dst));
      break;
    case DepthMode::kBounded: {
      const RelativeQuantizer& q = RelativeQuantizer::ForBound(h.bound_e4);
      std::size_t used = 0;
      CCMD_RETURN_IF_ERROR(
          DecodePredictive(payload, h.width, h.height, q.num_codes() - 1, dst, &used));
      if (used != payload.size()) return Corrupt("trailing bytes after the depth data");
      const std::uint16_t* values = q.value_table();
      for (std::size_t i = 0; i < n; ++i) dst[i] = values[dst[i]];
      break;
    }
  }
  if (!samples.empty()) {
    if (UsesEq6(h.mode)) {
      for (std::size_t i = 0; i < n; ++i) {
        if (samples[i] > kEq6MaxCode) return Corrupt("eq. 6 code above 7300");
        dst[i] = DequantizeEq6(samples[i]);
      }
    } else {
      std::memcpy(dst, samples.data(), n * sizeof(std::uint16_t));
    }
  }
  if (header_out) *header_out = h;
  return image;
}

}  // namespace ccmd
