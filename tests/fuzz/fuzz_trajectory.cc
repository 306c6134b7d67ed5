// Fuzz target: the TUM trajectory reader (groundtruth.txt, estimated trajectories). An
// accepted trajectory is sorted by time, its poses are finite rigid motions, each the pose its
// line gives, and it survives writing and reading back.

#include <algorithm>
#include <string>

#include "libccmd/io/trajectory.h"
#include "libccmd/util/string_util.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  const std::string texts[] = {
      "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
      "1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986\n"
      "1305031098.6758 1.3543 0.6341 1.6360 0.6106 0.5986 -0.3316 -0.3990\n",
      "0.0 0 0 0 0 0 0 1\n2.5 1e-3 -2 3 0.5 0.5 0.5 0.5\n1.0 0.1 0.2 0.3 0 0 1 0\n",
      "\n  # indented comment\n\t3 1 2 3 0 1 0 0  \r\n",
  };
  std::vector<std::vector<std::uint8_t>> seeds;
  for (const std::string& t : texts) seeds.emplace_back(t.begin(), t.end());
  return seeds;
}

std::vector<std::vector<std::uint8_t>> FuzzRegressions() {
  // A huge timestamp: its line was written cut short, running into the next.
  const std::string text =
      "2222222222222222253878774129880535515822904467370591732755213627816206164295154019848345"
      "5394458184466971582916854330727764322063860176656917233895232311625817425963310197322329"
      "62418954028142435256673045427706134528 0.1 0 0 0 0 0 1\n"
      "3 -1e300 1e300 -1.5e308 0 0 0 1\n";
  // A quaternion whose norm overflows: it was read as the identity.
  const std::string quaternion = "0 0 0 0 0 1e200 0 1e200\n";
  return {std::vector<std::uint8_t>(text.begin(), text.end()),
          std::vector<std::uint8_t>(quaternion.begin(), quaternion.end())};
}

namespace {

// The rotation a line's quaternion stands for, computed independently of the reader.
struct Expected {
  double timestamp;
  Eigen::Vector3d t;
  Eigen::Matrix3d R;
};

std::vector<Expected> ExpectedPoses(const std::string& text) {
  std::vector<Expected> out;
  std::size_t start = 0;
  while (start < text.size()) {
    std::size_t end = text.find('\n', start);
    if (end == std::string::npos) end = text.size();
    const std::string_view content = Trim(std::string_view(text).substr(start, end - start));
    start = end + 1;
    if (content.empty() || content.front() == '#') continue;
    const auto fields = SplitWhitespace(content);
    double v[8];
    for (int i = 0; i < 8; ++i) v[i] = *ParseDouble(fields[i]);
    Eigen::Vector4d q(v[4], v[5], v[6], v[7]);
    q /= q.cwiseAbs().maxCoeff();  // no overflow in the norm
    q.normalize();
    out.push_back({v[0], Eigen::Vector3d(v[1], v[2], v[3]),
                   Eigen::Quaterniond(q[3], q[0], q[1], q[2]).toRotationMatrix()});
  }
  std::stable_sort(out.begin(), out.end(),
                   [](const Expected& a, const Expected& b) { return a.timestamp < b.timestamp; });
  return out;
}

}  // namespace

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const std::string text(reinterpret_cast<const char*>(data), size);
  StatusOr<Trajectory> trajectory = ParseTumTrajectory(text, "fuzz");
  if (!trajectory.ok()) return 0;
  const std::vector<fuzz::Expected> expected = fuzz::ExpectedPoses(text);
  if (expected.size() != trajectory->size()) fuzz::FuzzFail("number of poses");
  for (std::size_t i = 0; i < expected.size(); ++i) {
    const StampedPose& p = (*trajectory)[i];
    if (i > 0 && p.timestamp < (*trajectory)[i - 1].timestamp) fuzz::FuzzFail("not sorted");
    if (!p.T_world_cam.matrix().allFinite()) fuzz::FuzzFail("pose not finite");
    const Eigen::Matrix3d R = p.T_world_cam.linear();
    if ((R * R.transpose() - Eigen::Matrix3d::Identity()).norm() > 1e-9 || R.determinant() < 0) {
      fuzz::FuzzFail("rotation not orthonormal");
    }
    if (p.timestamp != expected[i].timestamp || p.T_world_cam.translation() != expected[i].t ||
        (R - expected[i].R).norm() > 1e-9) {
      fuzz::FuzzFail("pose differs from its line");
    }
  }
  // Written and read back, the same trajectory (to the precision written).
  StatusOr<Trajectory> again = ParseTumTrajectory(FormatTumTrajectory(*trajectory), "again");
  if (!again.ok() || again->size() != trajectory->size()) fuzz::FuzzFail("written and read back");
  return 0;
}
