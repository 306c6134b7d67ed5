#include "libccmd/sensors/openni2_source.h"

#include <OpenNI.h>

#include <chrono>
#include <cmath>
#include <mutex>
#include <sstream>
#include <thread>

#include "libccmd/sensors/frame_pairing.h"
#include "libccmd/sensors/pixel_formats.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"

// Under LeakSanitizer: OpenNI2 and its drivers keep allocations until the process exits
// (and OpenNI2 is never shut down here, see InitializeOpenNI); those are not ours to report.
#if defined(__SANITIZE_ADDRESS__)
#define CCMD_LSAN_ACTIVE 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define CCMD_LSAN_ACTIVE 1
#endif
#endif
#ifdef CCMD_LSAN_ACTIVE
extern "C" __attribute__((used, visibility("default"))) const char* __lsan_default_suppressions() {
  return "leak:libOpenNI2.so\nleak:/OpenNI2/Drivers/\nleak:libusb-1.0.so\n";
}
#endif

namespace ccmd {
namespace {

// OpenNI2 is initialised once per process and left loaded: shutting it down unloads the
// driver libraries, which some drivers do not survive while their threads still run.
Status InitializeOpenNI() {
  static std::once_flag once;
  static openni::Status status = openni::STATUS_OK;
  static std::string error;
  std::call_once(once, [] {
    status = openni::OpenNI::initialize();
    if (status != openni::STATUS_OK) error = openni::OpenNI::getExtendedError();
  });
  if (status != openni::STATUS_OK) return Internal("OpenNI2 initialisation failed: " + error);
  return Status::Ok();
}

// OpenNI2's last error on one line, without its tabs and newlines.
std::string LastError() {
  std::string text;
  for (const char c : std::string(openni::OpenNI::getExtendedError())) {
    const bool space = c == '\t' || c == '\n' || c == '\r' || c == ' ';
    if (space && (text.empty() || text.back() == ' ')) continue;
    text += space ? ' ' : c;
  }
  while (!text.empty() && text.back() == ' ') text.pop_back();
  return text;
}

const char* PixelFormatName(openni::PixelFormat format) {
  switch (format) {
    case openni::PIXEL_FORMAT_DEPTH_1_MM:
      return "DEPTH_1_MM";
    case openni::PIXEL_FORMAT_DEPTH_100_UM:
      return "DEPTH_100_UM";
    case openni::PIXEL_FORMAT_SHIFT_9_2:
      return "SHIFT_9_2";
    case openni::PIXEL_FORMAT_SHIFT_9_3:
      return "SHIFT_9_3";
    case openni::PIXEL_FORMAT_RGB888:
      return "RGB888";
    case openni::PIXEL_FORMAT_YUV422:
      return "YUV422";
    case openni::PIXEL_FORMAT_GRAY8:
      return "GRAY8";
    case openni::PIXEL_FORMAT_GRAY16:
      return "GRAY16";
    case openni::PIXEL_FORMAT_JPEG:
      return "JPEG";
    case openni::PIXEL_FORMAT_YUYV:
      return "YUYV";
  }
  return "unknown";
}

bool IsDepthFormat(openni::PixelFormat f) {
  return f == openni::PIXEL_FORMAT_DEPTH_1_MM || f == openni::PIXEL_FORMAT_DEPTH_100_UM;
}

bool IsColorFormat(openni::PixelFormat f) {
  return f == openni::PIXEL_FORMAT_RGB888 || f == openni::PIXEL_FORMAT_YUYV ||
         f == openni::PIXEL_FORMAT_YUV422 || f == openni::PIXEL_FORMAT_JPEG;
}

// The test driver that ships with OpenNI2 ("Dummy") does not join its frame threads when a
// stream stops; destroying the stream under a running thread crashes. Its threads tick every
// 33 ms, so a wait of a few ticks before destroying lets them finish. Only that driver.
bool IsDummyDriverUri(const std::string& uri) {
  return uri == "Dummy" || uri == "Oz" || uri == "PingPong";
}

std::string ModesText(const openni::SensorInfo* info) {
  if (info == nullptr) return "none";
  std::string text;
  const auto& modes = info->getSupportedVideoModes();
  for (int i = 0; i < modes.getSize() && i < 16; ++i) {
    if (!text.empty()) text += ", ";
    text += std::to_string(modes[i].getResolutionX()) + "x" +
            std::to_string(modes[i].getResolutionY()) + "@" + std::to_string(modes[i].getFps()) +
            " " + PixelFormatName(modes[i].getPixelFormat());
  }
  return text.empty() ? "none" : text;
}

// Finds a mode of `info` at the size and rate asked for whose pixel format `accept` takes,
// preferring formats earlier in `preference`.
std::optional<openni::VideoMode> FindMode(const openni::SensorInfo* info, int width, int height,
                                          int fps,
                                          const std::vector<openni::PixelFormat>& preference) {
  if (info == nullptr) return std::nullopt;
  const auto& modes = info->getSupportedVideoModes();
  for (const openni::PixelFormat wanted : preference) {
    for (int i = 0; i < modes.getSize(); ++i) {
      const openni::VideoMode& m = modes[i];
      if (m.getResolutionX() == width && m.getResolutionY() == height && m.getFps() == fps &&
          m.getPixelFormat() == wanted) {
        return m;
      }
    }
  }
  return std::nullopt;
}

bool SameMode(const openni::VideoMode& a, const openni::VideoMode& b) {
  return a.getResolutionX() == b.getResolutionX() && a.getResolutionY() == b.getResolutionY() &&
         a.getFps() == b.getFps() && a.getPixelFormat() == b.getPixelFormat();
}

}  // namespace

struct OpenNI2Source::Impl {
  openni::Device device;
  openni::VideoStream depth;
  openni::VideoStream color;
  openni::VideoFrameRef depth_frame;
  openni::VideoFrameRef color_frame;
  bool depth_started = false;
  bool color_started = false;
  int depth_total = -1;  // frames in a recording
  bool ended = false;    // the recording's last depth frame was handed out
  MjpegDecoder mjpeg;
  std::string uri;

  ~Impl() {
    if (depth_started) depth.stop();
    if (color_started) color.stop();
    depth_frame.release();
    color_frame.release();
    if (IsDummyDriverUri(uri) && (depth_started || color_started)) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    depth.destroy();
    color.destroy();
    if (device.isValid()) device.close();
  }

  // Reads the next frame of one stream, waiting at most `timeout_s`.
  Status ReadNext(openni::VideoStream* stream, openni::VideoFrameRef* frame, double timeout_s,
                  bool is_file, const char* role) {
    int ready = -1;
    openni::VideoStream* streams[1] = {stream};
    const openni::Status waited = openni::OpenNI::waitForAnyStream(
        streams, 1, &ready, static_cast<int>(std::lround(timeout_s * 1000)));
    if (waited == openni::STATUS_TIME_OUT) {
      if (is_file) return EndOfStream("recording " + uri + " ended");
      return Unavailable(std::string("openni2: no ") + role + " frame within " +
                         std::to_string(timeout_s) + " s (camera unplugged?)");
    }
    if (waited != openni::STATUS_OK) {
      return Unavailable(std::string("openni2: waiting for ") + role + ": " + LastError());
    }
    if (stream->readFrame(frame) != openni::STATUS_OK || !frame->isValid()) {
      return Unavailable(std::string("openni2: reading ") + role + ": " + LastError());
    }
    return Status::Ok();
  }
};

OpenNI2Source::OpenNI2Source() : impl_(new Impl()) {}
OpenNI2Source::~OpenNI2Source() = default;

StatusOr<std::unique_ptr<OpenNI2Source>> OpenNI2Source::Open(const OpenNI2Options& options) {
  const bool device_mode = options.width == 0 && options.height == 0;
  if ((!device_mode && (options.width < 1 || options.height < 1 || options.width > kMaxImageSide ||
                        options.height > kMaxImageSide)) ||
      !(options.fps > 0) || !(options.timeout_s > 0)) {
    return InvalidArgument("openni2: bad mode " + std::to_string(options.width) + "x" +
                           std::to_string(options.height) + "@" + std::to_string(options.fps));
  }
  const bool is_file =
      options.uri.size() > 4 && options.uri.compare(options.uri.size() - 4, 4, ".oni") == 0;
  if (is_file && !FileExists(options.uri)) {
    return NotFound("openni2: recording " + options.uri + " does not exist");
  }
  CCMD_RETURN_IF_ERROR(InitializeOpenNI());

  std::unique_ptr<OpenNI2Source> source(new OpenNI2Source());
  source->options_ = options;
  source->is_file_ = is_file;
  Impl& impl = *source->impl_;
  impl.uri = options.uri;

  const char* uri = options.uri.empty() ? openni::ANY_DEVICE : options.uri.c_str();
  if (impl.device.open(uri) != openni::STATUS_OK) {
    const std::string error = LastError();
    openni::Array<openni::DeviceInfo> devices;
    openni::OpenNI::enumerateDevices(&devices);
    if (is_file) return Corrupt("openni2: cannot play " + options.uri + ": " + error);
    std::string connected;
    bool listed = false;
    for (int i = 0; i < devices.getSize(); ++i) {
      connected += (connected.empty() ? "" : ", ") + std::string(devices[i].getUri());
      listed |= options.uri == devices[i].getUri();
    }
    if (devices.getSize() == 0) {
      return NotFound("openni2: no device " +
                      (options.uri.empty() ? std::string("found") : options.uri) +
                      " (is the camera plugged in and powered? " + error + ")");
    }
    if (!options.uri.empty() && !listed) {
      return NotFound("openni2: no device " + options.uri + "; connected: " + connected);
    }
    // The device is there but would not open: typically another program holds it.
    return Unavailable("openni2: " + connected + " could not be opened (in use by another " +
                       "program?): " + error);
  }

  const openni::SensorInfo* depth_info = impl.device.getSensorInfo(openni::SENSOR_DEPTH);
  const openni::SensorInfo* color_info = impl.device.getSensorInfo(openni::SENSOR_COLOR);
  if (depth_info == nullptr) return Unsupported("openni2: the device has no depth sensor");
  if (color_info == nullptr) return Unsupported("openni2: the device has no colour sensor");
  if (impl.depth.create(impl.device, openni::SENSOR_DEPTH) != openni::STATUS_OK) {
    return Unavailable("openni2: cannot create the depth stream: " + LastError());
  }
  if (impl.color.create(impl.device, openni::SENSOR_COLOR) != openni::STATUS_OK) {
    return Unavailable("openni2: cannot create the colour stream: " + LastError());
  }

  if (!is_file) {
    int width = options.width, height = options.height;
    int fps = static_cast<int>(std::lround(options.fps));
    const std::vector<openni::PixelFormat> depth_formats = {openni::PIXEL_FORMAT_DEPTH_1_MM,
                                                            openni::PIXEL_FORMAT_DEPTH_100_UM};
    if (device_mode) {
      width = 640, height = 480, fps = 30;
      if (!FindMode(depth_info, width, height, fps, depth_formats)) {
        const openni::VideoMode current = impl.depth.getVideoMode();
        width = current.getResolutionX();
        height = current.getResolutionY();
        fps = current.getFps();
      }
    }
    const auto depth_mode = FindMode(depth_info, width, height, fps, depth_formats);
    if (!depth_mode) {
      return Unsupported("openni2: no depth mode " + std::to_string(width) + "x" +
                         std::to_string(height) + "@" + std::to_string(fps) +
                         " in millimetres; the device offers " + ModesText(depth_info));
    }
    const auto color_mode = FindMode(color_info, width, height, fps,
                                     {openni::PIXEL_FORMAT_RGB888, openni::PIXEL_FORMAT_YUYV,
                                      openni::PIXEL_FORMAT_YUV422, openni::PIXEL_FORMAT_JPEG});
    if (!color_mode) {
      return Unsupported("openni2: no colour mode " + std::to_string(width) + "x" +
                         std::to_string(height) + "@" + std::to_string(fps) +
                         "; the device offers " + ModesText(color_info));
    }
    // Set a mode only when the stream is not already in it (some drivers cannot change
    // modes at all); a driver that lists a mode and then refuses it has the final word.
    if (!SameMode(impl.depth.getVideoMode(), *depth_mode) &&
        impl.depth.setVideoMode(*depth_mode) != openni::STATUS_OK) {
      return Unsupported("openni2: depth mode refused: " + LastError());
    }
    if (!SameMode(impl.color.getVideoMode(), *color_mode) &&
        impl.color.setVideoMode(*color_mode) != openni::STATUS_OK) {
      return Unsupported("openni2: colour mode refused: " + LastError());
    }
  }

  // Mirroring, registration and sync are best effort: drivers that cannot do them say so
  // (mirroring off by default is the common case), and the log says what was not done.
  impl.depth.setMirroringEnabled(false);
  impl.color.setMirroringEnabled(false);
  bool registered = false;
  if (options.register_depth && !is_file) {
    if (impl.device.isImageRegistrationModeSupported(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR) &&
        impl.device.setImageRegistrationMode(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR) ==
            openni::STATUS_OK) {
      registered = true;
    } else {
      CCMD_LOG(WARNING) << "openni2: the device cannot register depth to colour; colour and "
                           "depth will be slightly misaligned";
    }
  }
  if (options.sync && !is_file && impl.device.setDepthColorSyncEnabled(true) != openni::STATUS_OK) {
    CCMD_LOG(WARNING) << "openni2: no hardware frame sync (" << LastError()
                      << "); pairing by timestamp only";
  }

  if (is_file) {
    openni::PlaybackControl* playback = impl.device.getPlaybackControl();
    if (playback != nullptr) {
      // Real-time playback: a recording stands in for the camera it was made with.
      playback->setSpeed(1.0f);
      playback->setRepeatEnabled(false);
      impl.depth_total = playback->getNumberOfFrames(impl.depth);
      source->frame_count_ = impl.depth_total;
    }
  }

  if (impl.depth.start() != openni::STATUS_OK) {
    return Unavailable("openni2: cannot start the depth stream: " + LastError());
  }
  impl.depth_started = true;
  if (impl.color.start() != openni::STATUS_OK) {
    return Unavailable("openni2: cannot start the colour stream: " + LastError());
  }
  impl.color_started = true;

  const openni::VideoMode depth_mode = impl.depth.getVideoMode();
  const openni::VideoMode color_mode = impl.color.getVideoMode();
  if (!IsDepthFormat(depth_mode.getPixelFormat())) {
    return Unsupported(std::string("openni2: depth pixel format ") +
                       PixelFormatName(depth_mode.getPixelFormat()) + " is not in millimetres");
  }
  if (!IsColorFormat(color_mode.getPixelFormat())) {
    return Unsupported(std::string("openni2: colour pixel format ") +
                       PixelFormatName(color_mode.getPixelFormat()) + " is not supported");
  }
  const int width = depth_mode.getResolutionX();
  const int height = depth_mode.getResolutionY();
  const double fps = depth_mode.getFps() > 0 ? depth_mode.getFps() : options.fps;

  if (options.camera) {
    source->camera_ = *options.camera;
    if (source->camera_.width != width || source->camera_.height != height) {
      CCMD_LOG(WARNING) << "camera config is for " << source->camera_.width << "x"
                        << source->camera_.height << ", the depth stream is " << width << "x"
                        << height << ": scaling the intrinsics";
      source->camera_ = source->camera_.Resized(width, height);
    }
  } else {
    // Registered depth has the colour camera's geometry.
    const openni::VideoStream& geometry = registered ? impl.color : impl.depth;
    const double hfov = geometry.getHorizontalFieldOfView();
    const double vfov = geometry.getVerticalFieldOfView();
    PinholeCamera camera;
    camera.width = width;
    camera.height = height;
    if (hfov > 0.1 && hfov < 3.0 && vfov > 0.1 && vfov < 3.0) {
      camera.fx = width / 2.0 / std::tan(hfov / 2.0);
      camera.fy = height / 2.0 / std::tan(vfov / 2.0);
    } else {
      // No usable field of view (recordings from some drivers): a typical 58 degree lens.
      CCMD_LOG(WARNING) << "openni2: no field of view from the device; assuming 58 x 45 degrees";
      camera.fx = width / 2.0 / std::tan(58.0 * M_PI / 360.0);
      camera.fy = camera.fx;
    }
    camera.cx = width / 2.0 - 0.5;
    camera.cy = height / 2.0 - 0.5;
    camera.depth_map_factor = 1000.0;
    source->camera_ = camera;
  }
  source->camera_.fps = fps;
  source->tolerance_ =
      options.pair_tolerance_s > 0 ? options.pair_tolerance_s : DefaultPairTolerance(fps);

  std::ostringstream description;
  description << "openni2 " << (options.uri.empty() ? std::string("(first device)") : options.uri)
              << " depth " << width << "x" << height << "@" << fps << " "
              << PixelFormatName(depth_mode.getPixelFormat()) << ", colour "
              << color_mode.getResolutionX() << "x" << color_mode.getResolutionY() << " "
              << PixelFormatName(color_mode.getPixelFormat()) << (registered ? ", registered" : "");
  source->description_ = description.str();
  CCMD_LOG(INFO) << source->description_;
  return source;
}

Status OpenNI2Source::Fail(Status status) {
  failed_ = status;
  return status;
}

Status OpenNI2Source::Read(RgbdFrame* frame) {
  if (!failed_.ok()) return failed_;
  Impl& impl = *impl_;
  if (impl.ended) return Fail(EndOfStream("recording " + options_.uri + " ended"));
  const int max_drops = static_cast<int>(6 * std::max(1.0, camera_.fps));
  for (int drops = 0;; ++drops) {
    if (drops > max_drops) {
      return Fail(Unsupported("openni2: colour and depth timestamps never came within " +
                              std::to_string(tolerance_ * 1e3) + " ms of each other"));
    }
    if (!impl.color_frame.isValid()) {
      CCMD_RETURN_IF_ERROR(Fail(
          impl.ReadNext(&impl.color, &impl.color_frame, options_.timeout_s, is_file_, "colour")));
    }
    if (!impl.depth_frame.isValid()) {
      CCMD_RETURN_IF_ERROR(Fail(
          impl.ReadNext(&impl.depth, &impl.depth_frame, options_.timeout_s, is_file_, "depth")));
    }
    const double color_time = impl.color_frame.getTimestamp() * 1e-6;
    const double depth_time = impl.depth_frame.getTimestamp() * 1e-6;
    const PairStep step = NextPairStep(color_time, depth_time, tolerance_);
    if (step == PairStep::kAdvanceColor) {
      ++stats_.unpaired_dropped;
      impl.color_frame.release();
      continue;
    }
    if (step == PairStep::kAdvanceDepth) {
      ++stats_.unpaired_dropped;
      impl.depth_frame.release();
      continue;
    }

    const openni::VideoFrameRef& d = impl.depth_frame;
    const openni::VideoFrameRef& c = impl.color_frame;
    cv::Mat depth_mm, bgr;
    const double unit =
        d.getVideoMode().getPixelFormat() == openni::PIXEL_FORMAT_DEPTH_100_UM ? 1e-4 : 1e-3;
    Status status = ConvertZ16ToMillimetres(
        static_cast<const std::uint8_t*>(d.getData()), static_cast<std::size_t>(d.getDataSize()),
        {d.getWidth(), d.getHeight(), d.getStrideInBytes()}, unit, &depth_mm);
    if (status.ok()) {
      const auto* data = static_cast<const std::uint8_t*>(c.getData());
      const auto size = static_cast<std::size_t>(c.getDataSize());
      const PlaneGeometry plane{c.getWidth(), c.getHeight(), c.getStrideInBytes()};
      switch (c.getVideoMode().getPixelFormat()) {
        case openni::PIXEL_FORMAT_RGB888:
          status = ConvertRgb24ToBgr(data, size, plane, &bgr);
          break;
        case openni::PIXEL_FORMAT_YUYV:
          status = ConvertYuyvToBgr(data, size, plane, &bgr);
          break;
        case openni::PIXEL_FORMAT_YUV422:
          status = ConvertUyvyToBgr(data, size, plane, &bgr);
          break;
        case openni::PIXEL_FORMAT_JPEG:
          status = impl.mjpeg.Decode(data, size, c.getWidth(), c.getHeight(), &bgr);
          break;
        default:
          status = Unsupported("openni2: colour pixel format changed");
          break;
      }
    }
    const int depth_index = d.getFrameIndex();
    impl.color_frame.release();
    impl.depth_frame.release();
    if (impl.depth_total > 0 && depth_index >= impl.depth_total) impl.ended = true;
    if (!status.ok()) {
      ++stats_.damaged_dropped;
      CCMD_LOG(DEBUG) << "openni2: dropping a damaged pair: " << status.ToString();
      if (impl.ended) return Fail(EndOfStream("recording " + options_.uri + " ended"));
      continue;
    }
    frame->index = next_index_++;
    frame->timestamp = color_time;
    frame->depth_time_offset = depth_time - color_time;
    frame->bgr = ResizeColorToDepth(bgr, depth_mm.size());
    frame->depth_mm = depth_mm;
    ++stats_.frames;
    return Status::Ok();
  }
}

StatusOr<std::vector<OpenNI2DeviceInfo>> ListOpenNI2Devices() {
  CCMD_RETURN_IF_ERROR(InitializeOpenNI());
  openni::Array<openni::DeviceInfo> devices;
  openni::OpenNI::enumerateDevices(&devices);
  std::vector<OpenNI2DeviceInfo> result;
  for (int i = 0; i < devices.getSize(); ++i) {
    OpenNI2DeviceInfo info;
    info.uri = devices[i].getUri();
    info.vendor = devices[i].getVendor();
    info.name = devices[i].getName();
    info.usb_vendor_id = devices[i].getUsbVendorId();
    info.usb_product_id = devices[i].getUsbProductId();
    openni::Device device;
    if (device.open(devices[i].getUri()) != openni::STATUS_OK) {
      info.open_status = Unavailable("cannot open: " + LastError());
      result.push_back(std::move(info));
      continue;
    }
    info.registration_supported =
        device.isImageRegistrationModeSupported(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR);
    const std::pair<openni::SensorType, const char*> sensors[] = {{openni::SENSOR_DEPTH, "depth"},
                                                                  {openni::SENSOR_COLOR, "colour"},
                                                                  {openni::SENSOR_IR, "ir"}};
    for (const auto& [type, name] : sensors) {
      const openni::SensorInfo* sensor = device.getSensorInfo(type);
      if (sensor == nullptr) continue;
      const auto& modes = sensor->getSupportedVideoModes();
      for (int m = 0; m < modes.getSize(); ++m) {
        info.modes.push_back({name, modes[m].getResolutionX(), modes[m].getResolutionY(),
                              modes[m].getFps(), PixelFormatName(modes[m].getPixelFormat())});
      }
    }
    device.close();
    result.push_back(std::move(info));
  }
  return result;
}

}  // namespace ccmd
