#include "libccmd/io/tum_dataset.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>

#include "libccmd/geometry/pose.h"
#include "libccmd/io/config.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"

namespace ccmd {

Status TumOptions::Validate() const {
  if (!(max_time_difference > 0) || !std::isfinite(max_time_difference)) {
    return InvalidArgument("colour-depth association needs a positive time difference");
  }
  if (!(groundtruth_max_gap > 0) || !std::isfinite(groundtruth_max_gap)) {
    return InvalidArgument("ground-truth gap must be positive");
  }
  if (!(depth_map_factor >= 0) || !std::isfinite(depth_map_factor)) {
    return InvalidArgument("depth map factor must be >= 0 (0: from the camera)");
  }
  return Status::Ok();
}

void TumOptions::Describe(OptionsWriter* out) const {
  out->Add("max_time_difference", max_time_difference);
  out->Add("groundtruth_max_gap", groundtruth_max_gap);
  out->Add("depth_map_factor", depth_map_factor);
}

StatusOr<std::vector<TimedFile>> ReadTimedFileList(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, 1ull << 30));
  std::vector<TimedFile> files;
  CCMD_RETURN_IF_ERROR(ForEachDataLine(text, path, [&](const auto& fields) -> Status {
    if (fields.size() < 2) return Corrupt("expected 'timestamp path'");
    CCMD_ASSIGN_OR_RETURN(const double t, ParseDouble(fields[0]));
    files.push_back({t, std::string(fields[1])});
    return Status::Ok();
  }));
  std::stable_sort(files.begin(), files.end(), [](const TimedFile& a, const TimedFile& b) {
    return a.timestamp < b.timestamp;
  });
  return files;
}

std::vector<std::pair<std::size_t, std::size_t>> AssociateTimestamps(const std::vector<double>& a,
                                                                     const std::vector<double>& b,
                                                                     double max_difference,
                                                                     double offset) {
  // Candidate pairs within the tolerance. Walking both lists in time order with a sliding
  // window over b keeps this O(n log n + candidates) instead of the script's O(n*m).
  std::vector<std::size_t> b_order(b.size());
  for (std::size_t j = 0; j < b.size(); ++j) b_order[j] = j;
  std::sort(b_order.begin(), b_order.end(),
            [&](std::size_t x, std::size_t y) { return b[x] < b[y]; });
  struct Candidate {
    double difference;
    std::size_t i, j;
  };
  std::vector<Candidate> candidates;
  std::vector<std::size_t> a_order(a.size());
  for (std::size_t i = 0; i < a.size(); ++i) a_order[i] = i;
  std::sort(a_order.begin(), a_order.end(),
            [&](std::size_t x, std::size_t y) { return a[x] < a[y]; });
  std::size_t start = 0;
  for (const std::size_t i : a_order) {
    while (start < b_order.size() && b[b_order[start]] + offset <= a[i] - max_difference) ++start;
    for (std::size_t k = start; k < b_order.size(); ++k) {
      const double difference = std::abs(a[i] - (b[b_order[k]] + offset));
      if (b[b_order[k]] + offset >= a[i] + max_difference) break;
      if (difference < max_difference) candidates.push_back({difference, i, b_order[k]});
    }
  }
  std::stable_sort(
      candidates.begin(), candidates.end(),
      [](const Candidate& x, const Candidate& y) { return x.difference < y.difference; });
  std::vector<bool> a_used(a.size(), false), b_used(b.size(), false);
  std::vector<std::pair<std::size_t, std::size_t>> matches;
  for (const Candidate& c : candidates) {
    if (a_used[c.i] || b_used[c.j]) continue;
    a_used[c.i] = b_used[c.j] = true;
    matches.emplace_back(c.i, c.j);
  }
  std::sort(matches.begin(), matches.end());
  return matches;
}

namespace {

bool LooksLikeDepthPath(const std::string& path) { return path.find("depth") != std::string::npos; }

// associations.txt: "t1 path1 t2 path2" with the depth column told by its path.
Status ReadAssociations(const std::string& path, std::vector<TimedFile>* rgb,
                        std::vector<TimedFile>* depth) {
  CCMD_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, 1ull << 30));
  return ForEachDataLine(text, path, [&](const auto& fields) -> Status {
    if (fields.size() < 4) return Corrupt("expected 't path t path'");
    CCMD_ASSIGN_OR_RETURN(const double t1, ParseDouble(fields[0]));
    CCMD_ASSIGN_OR_RETURN(const double t2, ParseDouble(fields[2]));
    TimedFile first{t1, std::string(fields[1])};
    TimedFile second{t2, std::string(fields[3])};
    if (LooksLikeDepthPath(first.path) && !LooksLikeDepthPath(second.path))
      std::swap(first, second);
    rgb->push_back(first);
    depth->push_back(second);
    return Status::Ok();
  });
}

// 7-Scenes: frame-XXXXXX.{color,depth}.png, .pose.txt.
std::string SevenScenesFile(const std::string& folder, int index, const char* suffix) {
  char name[48];
  std::snprintf(name, sizeof(name), "frame-%06d.%s", index, suffix);
  return JoinPath(folder, name);
}

std::string SevenScenesColour(const std::string& folder, int index) {
  const std::string png = SevenScenesFile(folder, index, "color.png");
  return FileExists(png) ? png : SevenScenesFile(folder, index, "color.jpg");
}

// The numbers of a 7-Scenes folder's colour images, in order. A sequence's archive numbers
// its frames from 0; a folder holding part of one (frames 600-999 copied out) keeps the
// original numbers, and gaps are allowed.
std::vector<int> SevenScenesFrameNumbers(const std::string& folder) {
  std::vector<int> numbers;
  std::error_code error;
  for (const auto& entry : std::filesystem::directory_iterator(folder, error)) {
    const std::string name = entry.path().filename().string();
    int number = -1;
    if (std::sscanf(name.c_str(), "frame-%8d.color.", &number) != 1 || number < 0) continue;
    // Only the names the reader opens: six digits or more, no sign, png or jpg.
    if (JoinPath(folder, name) == SevenScenesColour(folder, number)) numbers.push_back(number);
  }
  std::sort(numbers.begin(), numbers.end());
  return numbers;
}

// A 4x4 camera-to-world matrix, its rotation made orthonormal (the files keep 6-7 digits).
StatusOr<Pose> ReadSevenScenesPose(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(std::string text, ReadFileToString(path, 1 << 16));
  std::replace(text.begin(), text.end(), '\n', ' ');
  const auto fields = SplitWhitespace(text);
  if (fields.size() != 16) return Corrupt(path + ": expected a 4x4 matrix (16 numbers)");
  Eigen::Matrix4d m;
  for (int k = 0; k < 16; ++k) {
    auto v = ParseDouble(fields[k]);
    if (!v.ok()) return v.status().WithContext(path);
    if (!std::isfinite(*v)) return Corrupt(path + ": a pose entry is not finite");
    m(k / 4, k % 4) = *v;
  }
  Pose T = Pose::Identity();
  T.linear() = m.topLeftCorner<3, 3>();
  T.translation() = m.topRightCorner<3, 1>();
  const Pose rigid = Orthonormalized(T);
  if ((T.linear() - rigid.linear()).cwiseAbs().maxCoeff() > 0.01) {
    return Corrupt(path + ": the matrix's rotation is not a rotation");
  }
  return rigid;
}

// ICL-NUIM's release numbers its frames (0, 1, 2, ...) where timestamps go, in its
// associations and in its ground truth alike: consecutive whole numbers.
bool FrameNumbers(const std::vector<TimedFile>& files) {
  if (files.size() < 2) return false;
  for (std::size_t i = 0; i < files.size(); ++i) {
    if (files[i].timestamp != std::floor(files[i].timestamp)) return false;
    if (i > 0 && files[i].timestamp != files[i - 1].timestamp + 1) return false;
  }
  return true;
}

// The ground truth of a folder: groundtruth.txt, else the one *.gt.freiburg ICL-NUIM's
// release puts beside its frames ("" when there is neither, or several).
std::string GroundTruthFile(const std::string& folder) {
  const std::string tum = JoinPath(folder, "groundtruth.txt");
  if (FileExists(tum)) return tum;
  std::string found;
  std::error_code error;
  for (const auto& entry : std::filesystem::directory_iterator(folder, error)) {
    const std::string name = entry.path().filename().string();
    const std::string suffix = ".gt.freiburg";
    if (name.size() <= suffix.size() ||
        name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0) {
      continue;
    }
    if (!found.empty()) return "";  // which one is meant is not clear
    found = entry.path().string();
  }
  return found;
}

}  // namespace

bool TumSequence::IsSevenScenesFolder(const std::string& folder) {
  const std::vector<int> numbers = SevenScenesFrameNumbers(folder);
  return std::any_of(numbers.begin(), numbers.end(), [&](int number) {
    return FileExists(SevenScenesFile(folder, number, "depth.png"));
  });
}

StatusOr<TumSequence> TumSequence::Open(const std::string& folder,
                                        const std::optional<PinholeCamera>& camera,
                                        const TumOptions& options) {
  if (!IsDirectory(folder)) return NotFound("dataset folder " + folder + " does not exist");
  TumSequence sequence;
  sequence.folder_ = folder;

  if (camera) {
    sequence.camera_ = *camera;
  } else if (FileExists(JoinPath(folder, "camera.yaml"))) {
    auto loaded = LoadCameraConfig(JoinPath(folder, "camera.yaml"));
    if (!loaded.ok()) return loaded.status();
    sequence.camera_ = *loaded;
  } else {
    const std::string guess = GuessCameraConfigName(folder);
    return InvalidArgument("no camera for " + folder +
                           ": pass a camera config (--config), e.g. configs/" +
                           (guess.empty() ? std::string("tum_fr1.yaml") : guess));
  }
  sequence.depth_map_factor_ =
      options.depth_map_factor > 0 ? options.depth_map_factor : sequence.camera_.depth_map_factor;

  std::vector<TimedFile> rgb, depth;
  const std::string rgb_list = JoinPath(folder, "rgb.txt");
  const std::string depth_list = JoinPath(folder, "depth.txt");
  std::vector<std::pair<std::size_t, std::size_t>> pairs;
  double frame_numbers_per_second = 0;  // the lists number frames instead of timing them
  if (FileExists(rgb_list) && FileExists(depth_list)) {
    CCMD_ASSIGN_OR_RETURN(rgb, ReadTimedFileList(rgb_list));
    CCMD_ASSIGN_OR_RETURN(depth, ReadTimedFileList(depth_list));
    std::vector<double> ta, tb;
    for (const auto& f : rgb) ta.push_back(f.timestamp);
    for (const auto& f : depth) tb.push_back(f.timestamp);
    pairs = AssociateTimestamps(ta, tb, options.max_time_difference);
  } else if (FileExists(JoinPath(folder, "associations.txt"))) {
    CCMD_RETURN_IF_ERROR(ReadAssociations(JoinPath(folder, "associations.txt"), &rgb, &depth));
    for (std::size_t i = 0; i < rgb.size(); ++i) pairs.emplace_back(i, i);
    // Frame numbers become seconds at the camera's rate (the release renders at 30 Hz), and
    // so do the ground truth's below.
    if (FrameNumbers(rgb) && FrameNumbers(depth) && sequence.camera_.fps > 0) {
      frame_numbers_per_second = sequence.camera_.fps;
      for (auto* files : {&rgb, &depth}) {
        for (TimedFile& f : *files) f.timestamp /= frame_numbers_per_second;
      }
    }
  } else if (IsSevenScenesFolder(folder)) {
    sequence.depth_map_factor_ = 1000.0;
    sequence.no_depth_code_ = 65535;
    for (const int i : SevenScenesFrameNumbers(folder)) {
      TumFrameInfo info;
      info.rgb_path = SevenScenesColour(folder, i);
      info.timestamp = info.depth_timestamp = 1.0 + i / 30.0;
      info.depth_path = SevenScenesFile(folder, i, "depth.png");
      const std::string pose = SevenScenesFile(folder, i, "pose.txt");
      if (FileExists(pose)) {
        CCMD_ASSIGN_OR_RETURN(const Pose T_world_cam, ReadSevenScenesPose(pose));
        info.T_world_cam_gt = T_world_cam;
        sequence.groundtruth_.push_back({info.timestamp, T_world_cam});
      }
      sequence.frames_.push_back(std::move(info));
    }
    return sequence;
  } else {
    return NotFound(folder +
                    " has neither rgb.txt + depth.txt nor associations.txt (nor 7-Scenes' "
                    "frame-NNNNNN.color.png and frame-NNNNNN.depth.png)");
  }
  if (pairs.empty()) {
    return Corrupt("no colour/depth pairs in " + folder + " within " +
                   std::to_string(options.max_time_difference) + " s");
  }

  const std::string gt_path = GroundTruthFile(folder);
  if (!gt_path.empty()) {
    CCMD_ASSIGN_OR_RETURN(sequence.groundtruth_, ReadTumTrajectory(gt_path));
    if (frame_numbers_per_second > 0) {
      for (StampedPose& p : sequence.groundtruth_) p.timestamp /= frame_numbers_per_second;
    }
  }
  for (const auto& [i, j] : pairs) {
    TumFrameInfo info;
    info.timestamp = rgb[i].timestamp;
    info.depth_timestamp = depth[j].timestamp;
    info.rgb_path = JoinPath(folder, rgb[i].path);
    info.depth_path = JoinPath(folder, depth[j].path);
    info.T_world_cam_gt =
        InterpolateTrajectory(sequence.groundtruth_, info.timestamp, options.groundtruth_max_gap);
    sequence.frames_.push_back(std::move(info));
  }
  return sequence;
}

Trajectory TumSequence::GroundTruthAtFrames() const {
  Trajectory trajectory;
  for (const TumFrameInfo& f : frames_) {
    if (f.T_world_cam_gt) trajectory.push_back({f.timestamp, *f.T_world_cam_gt});
  }
  return trajectory;
}

cv::Mat DepthToMillimetres(const cv::Mat& raw, double depth_map_factor) {
  cv::Mat mm;
  if (depth_map_factor == 1000.0) return raw.clone();
  raw.convertTo(mm, CV_16U, 1000.0 / depth_map_factor);  // rounds and saturates
  return mm;
}

cv::Mat SwapRedBlue(const cv::Mat& image) {
  if (image.channels() != 3) return image;
  cv::Mat swapped(image.size(), image.type());
  const int from_to[] = {0, 2, 1, 1, 2, 0};
  cv::mixChannels(&image, 1, &swapped, 1, from_to, 3);
  return swapped;
}

StatusOr<RgbdFrame> TumSequence::LoadFrame(std::size_t i) const {
  if (i >= frames_.size()) return OutOfRange("frame " + std::to_string(i) + " beyond the sequence");
  const TumFrameInfo& info = frames_[i];
  RgbdFrame frame;
  frame.index = static_cast<int>(i);
  frame.timestamp = info.timestamp;
  frame.depth_time_offset = info.depth_timestamp - info.timestamp;
  try {
    frame.bgr = cv::imread(info.rgb_path, cv::IMREAD_COLOR);
    const cv::Mat raw_depth = cv::imread(info.depth_path, cv::IMREAD_UNCHANGED);
    if (frame.bgr.empty()) return NotFound("cannot read colour image " + info.rgb_path);
    if (raw_depth.empty()) return NotFound("cannot read depth image " + info.depth_path);
    if (raw_depth.type() != CV_16UC1) {
      return Unsupported(info.depth_path + " is not a 16-bit single-channel image");
    }
    frame.depth_mm = DepthToMillimetres(raw_depth, depth_map_factor_);
    if (no_depth_code_ != 0) frame.depth_mm.setTo(0, raw_depth == no_depth_code_);
    if (!camera_.rgb) frame.bgr = SwapRedBlue(frame.bgr);
  } catch (const cv::Exception& e) {
    return Corrupt("cannot decode frame " + std::to_string(i) + ": " + e.msg);
  }
  if (frame.bgr.cols < frame.depth_mm.cols || frame.bgr.rows < frame.depth_mm.rows) {
    return Unsupported("colour image smaller than depth in frame " + std::to_string(i));
  }
  return frame;
}

std::string GuessCameraConfigName(const std::string& folder) {
  if (TumSequence::IsSevenScenesFolder(folder)) return "7scenes.yaml";
  std::string name = folder;
  while (!name.empty() && name.back() == '/') name.pop_back();
  name = name.substr(name.find_last_of('/') == std::string::npos ? 0 : name.find_last_of('/') + 1);
  std::transform(name.begin(), name.end(), name.begin(), ::tolower);
  if (name.find("freiburg1") != std::string::npos || name.find("fr1") != std::string::npos)
    return "tum_fr1.yaml";
  if (name.find("freiburg2") != std::string::npos || name.find("fr2") != std::string::npos)
    return "tum_fr2.yaml";
  if (name.find("freiburg3") != std::string::npos || name.find("fr3") != std::string::npos)
    return "tum_fr3.yaml";
  // ICL-NUIM's TUM-compatible archives are <scene>_traj<N>_frei_png (the office room's just
  // traj<N>_frei_png).
  if (name.find("living_room") != std::string::npos ||
      name.find("office_room") != std::string::npos || name.find("icl") != std::string::npos ||
      name.find("frei_png") != std::string::npos)
    return "icl_nuim.yaml";
  if (name.find("7scenes") != std::string::npos || name.find("redkitchen") != std::string::npos)
    return "7scenes.yaml";
  return "";
}

}  // namespace ccmd
