#include "libccmd/tracking/frame.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "libccmd/sensors/depth_registration.h"

namespace ccmd {

int TrackingFrame::TrackedPoints() const {
  int n = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (points[i] && !outlier[i] && !points[i]->bad()) ++n;
  }
  return n;
}

double KeypointDepthSigma(const cv::Mat& depth_mm, int x, int y, double z, double pixel_sigma,
                          const DepthNoise& noise) {
  const auto at = [&](int dx, int dy) { return 1e-3 * depth_mm.at<std::uint16_t>(y + dy, x + dx); };
  const double gx = 0.25 * (at(2, 0) - at(-2, 0)), gy = 0.25 * (at(0, 2) - at(0, -2));
  const double sensor = noise.Sigma(z), position = std::hypot(gx, gy) * pixel_sigma;
  return std::sqrt(sensor * sensor + position * position);
}

namespace {

// FAST finds corners on the pixel grid; the corner itself lies within half a pixel of it.
// Refines the finest octave's keypoints (where that half pixel matters most) to where the
// image gradients around them meet (cv::cornerSubPix); a keypoint that would move by more
// than a pixel is not a clean corner and stays where it was.
void RefineKeypoints(const cv::Mat& gray, std::vector<cv::KeyPoint>* keypoints) {
  std::vector<cv::Point2f> points;
  std::vector<std::size_t> index;
  for (std::size_t i = 0; i < keypoints->size(); ++i) {
    if ((*keypoints)[i].octave != 0) continue;
    points.push_back((*keypoints)[i].pt);
    index.push_back(i);
  }
  if (points.empty()) return;
  std::vector<cv::Point2f> refined = points;
  cv::cornerSubPix(gray, refined, cv::Size(2, 2), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 10, 0.01));
  for (std::size_t k = 0; k < points.size(); ++k) {
    const cv::Point2f d = refined[k] - points[k];
    if (d.x * d.x + d.y * d.y <= 1.0f) (*keypoints)[index[k]].pt = refined[k];
  }
}

// The depth (m) at a keypoint's own position, interpolated between the four pixels around it
// (valid and continuous there: the caller checked the 5x5 neighbourhood): on a slanted surface
// the nearest pixel's depth is off by the slope times up to half a pixel.
double DepthAt(const cv::Mat& depth_mm, const cv::Point2f& pt) {
  const int x0 = static_cast<int>(std::floor(pt.x)), y0 = static_cast<int>(std::floor(pt.y));
  const double fx = pt.x - x0, fy = pt.y - y0;
  const auto at = [&](int x, int y) { return 1e-3 * depth_mm.at<std::uint16_t>(y, x); };
  return (1 - fy) * ((1 - fx) * at(x0, y0) + fx * at(x0 + 1, y0)) +
         fy * ((1 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1));
}

// Where the point that colour pixel `pt` sees lies in a depth image taken from a nearby pose
// (`T_depth_colour` takes the colour image's camera frame to the depth image's): projected
// from the depth measured at the pixel itself (the translation of a few milliseconds makes
// the depth matter little), again from the depth found there where the two differ (a depth
// edge), and from the rotation alone where there is no depth. Lens distortion is left out: it
// changes a shift of a few pixels by hundredths of a pixel.
cv::Point2f WhereDepthSaw(const cv::Mat& depth_mm, const cv::Point2f& pt,
                          const PinholeCamera& camera, const Pose& T_depth_colour) {
  const Eigen::Vector3d ray((pt.x - camera.cx) / camera.fx, (pt.y - camera.cy) / camera.fy, 1.0);
  const auto project = [&](double z) {
    const Eigen::Vector3d Y = z > 0 ? T_depth_colour * (z * ray) : T_depth_colour.linear() * ray;
    return cv::Point2f(static_cast<float>(camera.fx * Y.x() / Y.z() + camera.cx),
                       static_cast<float>(camera.fy * Y.y() / Y.z() + camera.cy));
  };
  const auto depth_near = [&](const cv::Point2f& p) {
    const int x = cvRound(p.x), y = cvRound(p.y);
    if (x < 0 || y < 0 || x >= depth_mm.cols || y >= depth_mm.rows) return 0.0;
    return 1e-3 * depth_mm.at<std::uint16_t>(y, x);
  };
  const double z = depth_near(pt);
  const cv::Point2f at = project(z);
  const double z_there = depth_near(at);
  if (z_there > 0 && std::fabs(z_there - z) > 0.02 * z_there) return project(z_there);
  return at;
}

}  // namespace

Pose MotionOver(const Pose& velocity, double interval, double dt) {
  const double fraction = dt / interval;
  Pose T_later_now = Pose::Identity();
  T_later_now.linear() = RotationFromAngleAxis(fraction * AngleAxisFromRotation(velocity.linear()));
  T_later_now.translation() = fraction * velocity.translation();
  return T_later_now.inverse();
}

void UnrollKeypoints(const cv::Mat& depth_mm, const PinholeCamera& camera,
                     const RollingShutter& shutter, const TrackingOptions& options,
                     std::vector<cv::KeyPoint>* keypoints) {
  const double height = camera.height;
  for (cv::KeyPoint& keypoint : *keypoints) {
    const double dt = shutter.readout * ((keypoint.pt.y + 0.5) / height - 0.5);
    const Pose T_now_then = MotionOver(shutter.velocity, shutter.interval, dt);
    const Eigen::Vector2d raw(keypoint.pt.x, keypoint.pt.y);
    const Eigen::Vector2d ideal = camera.HasDistortion() ? camera.UndistortPixel(raw) : raw;
    const int x = cvRound(raw.x()), y = cvRound(raw.y());
    const double d = depth_mm.empty() || x < 0 || y < 0 || x >= depth_mm.cols || y >= depth_mm.rows
                         ? 0.0
                         : depth_mm.at<std::uint16_t>(y, x) * 1e-3;
    const bool has_depth = d >= options.min_depth && d <= options.max_depth;
    const Eigen::Vector3d seen = camera.BackProject(ideal.x(), ideal.y(), has_depth ? d : 1.0);
    // Without depth the point counts as far: only the rotation moves it.
    const Eigen::Vector3d now = has_depth ? T_now_then * seen : T_now_then.linear() * seen;
    if (!(now.z() > 0)) continue;
    const Eigen::Vector2d moved = camera.ProjectToImage(now);
    keypoint.pt.x = static_cast<float>(std::clamp(moved.x(), 0.0, camera.width - 1.0));
    keypoint.pt.y = static_cast<float>(std::clamp(moved.y(), 0.0, camera.height - 1.0));
  }
}

namespace {

// Gives each keypoint of `f` (raw pixels) its depth, the depth's sigma and the virtual right
// coordinate, then moves the keypoints to the ideal pinhole camera.
void AttachDepths(const cv::Mat& depth_mm, const OrbExtractor& orb, const PinholeCamera& camera,
                  const TrackingOptions& options, const Pose* T_colour_depth, FrameFeatures* out) {
  FrameFeatures& f = *out;
  f.depth.assign(f.keypoints.size(), 0.0f);
  f.depth_sigma.assign(f.keypoints.size(), 0.0f);
  f.u_right.assign(f.keypoints.size(), -1.0f);
  constexpr int kRadius = 2;
  const Pose T_depth_colour = T_colour_depth ? T_colour_depth->inverse() : Pose::Identity();
  for (std::size_t i = 0; i < f.keypoints.size(); ++i) {
    // Where the keypoint's point lies in the depth image (its own pixel, unless the depth was
    // taken apart from the colour).
    const cv::Point2f at = T_colour_depth
                               ? WhereDepthSaw(depth_mm, f.keypoints[i].pt, camera, T_depth_colour)
                               : f.keypoints[i].pt;
    const int x = cvRound(at.x), y = cvRound(at.y);
    if (x < kRadius || y < kRadius || x >= depth_mm.cols - kRadius || y >= depth_mm.rows - kRadius)
      continue;
    const double d = depth_mm.at<std::uint16_t>(y, x) * 1e-3;
    if (d < options.min_depth || d > options.max_depth) continue;
    // Corners often sit on depth edges, where a pixel of misregistration between colour and
    // depth (or the sensor's edge noise) gives the depth of the other surface. Depth counts
    // only where the 5x5 neighbourhood is valid and continuous: its depths span no more than
    // a slanted surface's (1 cm + 3 % of the depth) or the sensor's noise does (25 depths of
    // one surface span under 6 sigma; a D435 at 2 m has sigma = 17 mm).
    int lo = 65535, hi = 0;
    for (int dy = -kRadius; dy <= kRadius; ++dy) {
      const std::uint16_t* row = depth_mm.ptr<std::uint16_t>(y + dy);
      for (int dx = -kRadius; dx <= kRadius; ++dx) {
        const int v = row[x + dx];
        lo = std::min(lo, v);
        hi = std::max(hi, v);
      }
    }
    const DepthNoise& noise = options.depth_noise;
    const double span = std::max(0.01 + 0.03 * d, 6.0 * noise.Sigma(d));
    if (lo == 0 || (hi - lo) * 1e-3 > span) continue;
    f.depth[i] = static_cast<float>(DepthAt(depth_mm, at));
    if (T_colour_depth) {
      // That point's depth in the camera at the colour image's time.
      const Eigen::Vector3d ray((at.x - camera.cx) / camera.fx, (at.y - camera.cy) / camera.fy, 1);
      f.depth[i] = static_cast<float>((*T_colour_depth * (f.depth[i] * ray)).z());
    }
    const double pixel_sigma = noise.keypoint_offset * orb.scale()[f.keypoints[i].octave];
    f.depth_sigma[i] =
        static_cast<float>(KeypointDepthSigma(depth_mm, x, y, d, pixel_sigma, noise));
    f.u_right[i] = static_cast<float>(f.keypoints[i].pt.x - camera.bf / f.depth[i]);
  }
  // As ORB-SLAM does: features are found and depth looked up on the image as recorded (depth
  // is registered to it); from here on every keypoint is the pixel of the ideal pinhole camera.
  if (camera.HasDistortion()) {
    for (std::size_t i = 0; i < f.keypoints.size(); ++i) {
      cv::Point2f& pt = f.keypoints[i].pt;
      const Eigen::Vector2d ideal = camera.UndistortPixel(Eigen::Vector2d(pt.x, pt.y));
      if (f.depth[i] > 0) f.u_right[i] += static_cast<float>(ideal.x() - pt.x);
      pt = cv::Point2f(static_cast<float>(ideal.x()), static_cast<float>(ideal.y()));
    }
  }
}

}  // namespace

FrameFeatures ComputeFeatures(const cv::Mat& gray, const cv::Mat& depth_mm, const OrbExtractor& orb,
                              const PinholeCamera& camera, const TrackingOptions& options,
                              const Pose* T_colour_depth, const RollingShutter* shutter,
                              std::vector<cv::KeyPoint>* as_read) {
  OrbFeatures orb_features = orb.Extract(gray);
  FrameFeatures f;
  f.keypoints = std::move(orb_features.keypoints);
  if (options.subpixel_keypoints) RefineKeypoints(gray, &f.keypoints);
  if (as_read && (shutter || T_colour_depth)) *as_read = f.keypoints;
  if (shutter) UnrollKeypoints(depth_mm, camera, *shutter, options, &f.keypoints);
  f.descriptors = orb_features.descriptors;
  AttachDepths(depth_mm, orb, camera, options, T_colour_depth, &f);
  return f;
}

void MoveKeypointsAgain(TrackingFrame* frame, const RollingShutter& shutter,
                        const OrbExtractor& orb, const PinholeCamera& camera,
                        const TrackingOptions& options) {
  if (frame->keypoints_as_read.empty()) return;
  frame->features.keypoints = frame->keypoints_as_read;
  if (shutter.readout > 0)
    UnrollKeypoints(frame->depth_mm, camera, shutter, options, &frame->features.keypoints);
  AttachDepths(frame->depth_mm, orb, camera, options,
               frame->T_colour_depth ? &*frame->T_colour_depth : nullptr, &frame->features);
  frame->grid = FeatureGrid(frame->features.keypoints, camera.width, camera.height);
}

const cv::Mat& TrackingFrame::DepthAtColourTime(const PinholeCamera& camera) {
  if (!T_colour_depth || depth_mm.empty()) return depth_mm;
  if (depth_at_colour_time_.empty()) {
    depth_at_colour_time_ = DepthFromNearbyPose(depth_mm, camera, T_colour_depth->inverse());
  }
  return depth_at_colour_time_;
}

void TrackingFrame::HandDepthTo(Keyframe* keyframe) const {
  const bool moved = !depth_at_colour_time_.empty();
  keyframe->depth_mm = moved ? depth_at_colour_time_ : depth_mm;
  keyframe->T_colour_depth = moved ? std::nullopt : T_colour_depth;
}

std::unique_ptr<TrackingFrame> MakeFrame(const RgbdFrame& input, const OrbExtractor& orb,
                                         const PinholeCamera& camera,
                                         const TrackingOptions& options,
                                         const std::optional<Pose>& T_colour_depth,
                                         const RollingShutter* shutter) {
  auto frame = std::make_unique<TrackingFrame>();
  frame->index = input.index;
  frame->timestamp = input.timestamp;
  frame->bgr = input.bgr;
  frame->depth_mm = input.depth_mm;
  frame->T_colour_depth = T_colour_depth;
  frame->depth_time_offset = input.depth_time_offset;
  cv::Mat gray;
  if (input.bgr.size() != input.depth_mm.size()) {
    cv::Mat resized;
    cv::resize(input.bgr, resized, input.depth_mm.size(), 0, 0, cv::INTER_AREA);
    cv::cvtColor(resized, gray, cv::COLOR_BGR2GRAY);
    frame->bgr = resized;
  } else {
    cv::cvtColor(input.bgr, gray, cv::COLOR_BGR2GRAY);
  }
  frame->features = ComputeFeatures(gray, input.depth_mm, orb, camera, options,
                                    T_colour_depth ? &*T_colour_depth : nullptr, shutter,
                                    &frame->keypoints_as_read);
  frame->grid = FeatureGrid(frame->features.keypoints, camera.width, camera.height);
  frame->points.assign(frame->features.keypoints.size(), nullptr);
  frame->outlier.assign(frame->features.keypoints.size(), false);
  return frame;
}

}  // namespace ccmd
