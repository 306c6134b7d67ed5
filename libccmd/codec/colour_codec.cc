#include "libccmd/codec/colour_codec.h"

#include <turbojpeg.h>

#include <memory>

#include <opencv2/imgproc.hpp>

namespace ccmd {
namespace {

struct HandleCloser {
  void operator()(void* handle) const {
    if (handle) tjDestroy(handle);
  }
};
using Handle = std::unique_ptr<void, HandleCloser>;

std::string TurboJpegError(tjhandle handle) { return std::string(tjGetErrorStr2(handle)); }

}  // namespace

Status ColourEncodeOptions::Validate() const {
  if (quality < 1 || quality > 100) return InvalidArgument("JPEG quality must be in 1..100");
  if (downsample != 1 && downsample != 2 && downsample != 4) {
    return InvalidArgument("downsample must be 1, 2 or 4");
  }
  return Status::Ok();
}

void ColourEncodeOptions::Describe(OptionsWriter* out) const {
  out->Add("quality", quality);
  out->Add("downsample", downsample);
}

Status ColourDecodeOptions::Validate() const {
  if (max_pixels == 0) return InvalidArgument("max_pixels must be positive");
  return Status::Ok();
}

void ColourDecodeOptions::Describe(OptionsWriter* out) const { out->Add("max_pixels", max_pixels); }

StatusOr<cv::Mat> PrepareColour(const cv::Mat& bgr, cv::Size depth_size, int downsample) {
  if (bgr.type() != CV_8UC3 || bgr.empty()) return InvalidArgument("colour must be CV_8UC3 BGR");
  if (downsample != 1 && downsample != 2 && downsample != 4) {
    return InvalidArgument("downsample must be 1, 2 or 4");
  }
  cv::Mat image = bgr;
  if (!depth_size.empty() && depth_size != bgr.size()) {
    cv::resize(bgr, image, depth_size, 0, 0, cv::INTER_AREA);
  }
  if (downsample > 1) {
    cv::Mat small;
    cv::resize(image, small, cv::Size(image.cols / downsample, image.rows / downsample), 0, 0,
               cv::INTER_AREA);
    image = small;
  }
  if (!image.isContinuous()) image = image.clone();
  return image;
}

StatusOr<std::vector<std::uint8_t>> EncodeColour(const cv::Mat& bgr, cv::Size depth_size,
                                                 const ColourEncodeOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  CCMD_ASSIGN_OR_RETURN(const cv::Mat image, PrepareColour(bgr, depth_size, options.downsample));
  Handle handle(tjInitCompress());
  if (!handle) return Internal("cannot create a TurboJPEG compressor");
  unsigned char* jpeg = nullptr;
  unsigned long size = 0;
  const int rc = tjCompress2(handle.get(), image.ptr<unsigned char>(0), image.cols,
                             static_cast<int>(image.step[0]), image.rows, TJPF_BGR, &jpeg, &size,
                             TJSAMP_420, options.quality, TJFLAG_FASTDCT);
  if (rc != 0) {
    if (jpeg) tjFree(jpeg);
    return Internal("JPEG compression failed: " + TurboJpegError(handle.get()));
  }
  std::vector<std::uint8_t> out(jpeg, jpeg + size);
  tjFree(jpeg);
  return out;
}

StatusOr<cv::Mat> DecodeColour(std::span<const std::uint8_t> jpeg,
                               const ColourDecodeOptions& options) {
  if (jpeg.empty()) return Corrupt("empty JPEG");
  Handle handle(tjInitDecompress());
  if (!handle) return Internal("cannot create a TurboJPEG decompressor");
  int width = 0, height = 0, subsampling = 0, colourspace = 0;
  // TurboJPEG takes a non-const buffer in its older signatures but does not write to it.
  auto* data = const_cast<unsigned char*>(jpeg.data());
  if (tjDecompressHeader3(handle.get(), data, jpeg.size(), &width, &height, &subsampling,
                          &colourspace) != 0) {
    return Corrupt("bad JPEG header: " + TurboJpegError(handle.get()));
  }
  if (width <= 0 || height <= 0 ||
      static_cast<std::uint64_t>(width) * height > options.max_pixels) {
    return OutOfRange("JPEG of " + std::to_string(width) + "x" + std::to_string(height) +
                      " exceeds the limit of " + std::to_string(options.max_pixels) + " pixels");
  }
  cv::Mat image(height, width, CV_8UC3);
  if (tjDecompress2(handle.get(), data, jpeg.size(), image.ptr<unsigned char>(0), width,
                    static_cast<int>(image.step[0]), height, TJPF_BGR,
                    TJFLAG_FASTDCT | TJFLAG_LIMITSCANS | TJFLAG_STOPONWARNING) != 0) {
    return Corrupt("bad JPEG data: " + TurboJpegError(handle.get()));
  }
  return image;
}

}  // namespace ccmd
