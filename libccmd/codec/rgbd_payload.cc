#include "libccmd/codec/rgbd_payload.h"

namespace ccmd {

Status RgbdEncodeOptions::Validate() const {
  if (downsample != 1 && downsample != 2 && downsample != 4) {
    return InvalidArgument("downsample must be 1, 2 or 4");
  }
  if (static_cast<int>(depth_mode) >= kNumDepthModes) return InvalidArgument("unknown depth mode");
  if (bound_e4 < 1 || bound_e4 > 2000) return InvalidArgument("bound_e4 must be in 1..2000");
  if (jpeg_quality < 1 || jpeg_quality > 100) {
    return InvalidArgument("JPEG quality must be in 1..100");
  }
  return Status::Ok();
}

void RgbdEncodeOptions::Describe(OptionsWriter* out) const {
  out->Add("downsample", downsample);
  out->Add("depth_mode", DepthModeName(depth_mode));
  out->Add("bound_e4", bound_e4);
  out->Add("jpeg_quality", jpeg_quality);
}

Status RgbdDecodeOptions::Validate() const {
  if (max_pixels == 0) return InvalidArgument("max_pixels must be positive");
  return Status::Ok();
}

void RgbdDecodeOptions::Describe(OptionsWriter* out) const { out->Add("max_pixels", max_pixels); }

StatusOr<RgbdPayload> EncodeRgbdPayload(const RgbdFrame& frame, const RgbdEncodeOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  DepthEncodeOptions depth;
  depth.mode = options.depth_mode;
  depth.downsample = options.downsample;
  depth.bound_e4 = options.bound_e4;
  ColourEncodeOptions colour;
  colour.quality = options.jpeg_quality;
  colour.downsample = options.downsample;
  RgbdPayload payload;
  payload.downsample = static_cast<std::uint8_t>(options.downsample);
  payload.depth_mode = static_cast<std::uint8_t>(options.depth_mode);
  CCMD_ASSIGN_OR_RETURN(payload.depth, EncodeDepth(frame.depth_mm, depth));
  CCMD_ASSIGN_OR_RETURN(payload.colour_jpeg,
                        EncodeColour(frame.bgr, frame.depth_mm.size(), colour));
  return payload;
}

StatusOr<DecodedRgbd> DecodeRgbdPayload(const RgbdPayload& payload,
                                        const RgbdDecodeOptions& options) {
  DepthHeader header;
  DepthDecodeOptions depth_options;
  depth_options.max_pixels = options.max_pixels;
  DecodedRgbd out;
  CCMD_ASSIGN_OR_RETURN(out.depth_mm, DecodeDepth(payload.depth, depth_options, &header));
  if (header.downsample != payload.downsample ||
      static_cast<int>(header.mode) != payload.depth_mode) {
    return Corrupt("RGB-D payload fields disagree with its depth bitstream");
  }
  ColourDecodeOptions colour_options;
  colour_options.max_pixels = options.max_pixels;
  CCMD_ASSIGN_OR_RETURN(out.bgr, DecodeColour(payload.colour_jpeg, colour_options));
  if (out.bgr.size() != out.depth_mm.size()) {
    return Corrupt("RGB-D payload: colour " + std::to_string(out.bgr.cols) + "x" +
                   std::to_string(out.bgr.rows) + " and depth " +
                   std::to_string(out.depth_mm.cols) + "x" + std::to_string(out.depth_mm.rows) +
                   " differ");
  }
  out.downsample = header.downsample;
  return out;
}

}  // namespace ccmd
