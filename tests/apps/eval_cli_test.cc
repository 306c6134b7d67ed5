// ccmd_eval as users run it: exit codes, printed ranges and JSON fields.

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include "libccmd/io/ply.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using testing::ProgramPath;
using testing::RunCommand;

// Runs `ccmd_eval recon ARGS` on the folder's ref.ply and rec.ply: the JSON it wrote, or the
// error (with the program's output) when it failed.
StatusOr<Json> RunRecon(const testing::TempDir& dir, const std::string& args, std::string* out) {
  const int status =
      RunCommand(ProgramPath("ccmd_eval") + " recon " + args + " --ref " + dir.File("ref.ply") +
                     " --rec " + dir.File("rec.ply") + " --json " + dir.File("r.json"),
                 out);
  if (status != 0) return Internal("ccmd_eval recon exited with " + std::to_string(status));
  return ReadJsonFile(dir.File("r.json"));
}

TEST(EvalCliTest, SplitPrintsFirstLastPerSegment) {
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_eval") + " split --frames 600 --agents 3", &out), 0)
      << out;
  EXPECT_EQ(out, "0 214\n193 407\n386 599\n");
  EXPECT_NE(RunCommand(ProgramPath("ccmd_eval") + " split --frames 3 --agents 3", &out), 0);
  EXPECT_NE(out.find("too few"), std::string::npos) << out;
}

TEST(EvalCliTest, AteWritesTheDocumentedJsonFields) {
  testing::TempDir dir;
  Trajectory gt, est;
  for (int i = 0; i < 60; ++i) {
    Pose p = Pose::Identity();
    p.translation() = Eigen::Vector3d(std::cos(i * 0.1), std::sin(i * 0.1), 0);
    gt.push_back({1.0 + i / 30.0, p});
    p.translation().z() += (i % 2 ? 0.01 : -0.01);
    est.push_back({1.0 + i / 30.0, p});
  }
  ASSERT_TRUE(WriteTumTrajectory(gt, dir.File("gt.txt")).ok());
  ASSERT_TRUE(WriteTumTrajectory(est, dir.File("est.txt")).ok());
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_eval") + " ate --gt " + dir.File("gt.txt") + " --est " +
                           dir.File("est.txt") + " --json " + dir.File("ate.json"),
                       &out),
            0)
      << out;
  auto json = ReadJsonFile(dir.File("ate.json"));
  ASSERT_TRUE(json.ok());
  for (const char* key : {"ate_rmse_m", "ate_mean_m", "ate_max_m", "matched"}) {
    EXPECT_TRUE(json->Has(key)) << key;
  }
  EXPECT_EQ(json->Get("matched")->number(), 60);
  EXPECT_NEAR(json->Get("ate_rmse_m")->number(), 0.01, 5e-4);
  EXPECT_NE(RunCommand(ProgramPath("ccmd_eval") + " ate --gt " + dir.File("missing.txt") +
                           " --est " + dir.File("est.txt"),
                       &out),
            0);
  EXPECT_NE(out.find("missing.txt"), std::string::npos) << out;
}

TEST(EvalCliTest, AteReadsTheGroundTruthOfADatasetFolder) {
  // A 7-Scenes sequence as unpacked: one 4x4 camera-to-world matrix per frame, frames 1/30 s
  // apart from t = 1 s; the estimate is the same circle 1 cm above.
  testing::TempDir dir;
  const std::string seq = dir.File("seq-01");
  ASSERT_TRUE(MakeDirectories(seq).ok());
  Trajectory est;
  for (int i = 0; i < 40; ++i) {
    char stem[32];
    std::snprintf(stem, sizeof(stem), "/frame-%06d.", i);
    const double x = std::cos(i * 0.1), y = std::sin(i * 0.1);
    ASSERT_TRUE(WriteFileAtomic(seq + stem + "color.png", "").ok());  // only the names count
    ASSERT_TRUE(WriteFileAtomic(seq + stem + "depth.png", "").ok());
    ASSERT_TRUE(WriteFileAtomic(seq + stem + "pose.txt", "1 0 0 " + std::to_string(x) + "\n0 1 0 " +
                                                             std::to_string(y) +
                                                             "\n0 0 1 0\n0 0 0 1\n")
                    .ok());
    Pose p = Pose::Identity();
    p.translation() = Eigen::Vector3d(x, y, 0.01);
    est.push_back({1.0 + i / 30.0, p});
  }
  ASSERT_TRUE(WriteTumTrajectory(est, dir.File("est.txt")).ok());
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_eval") + " ate --gt " + seq + " --est " +
                           dir.File("est.txt") + " --json " + dir.File("ate.json"),
                       &out),
            0)
      << out;
  auto json = ReadJsonFile(dir.File("ate.json"));
  ASSERT_TRUE(json.ok());
  EXPECT_EQ(json->Get("matched")->number(), 40);
  EXPECT_LT(json->Get("ate_rmse_m")->number(), 1e-5);  // a shift is aligned away
  EXPECT_NE(RunCommand(ProgramPath("ccmd_eval") + " ate --gt " + dir.path() + " --est " +
                           dir.File("est.txt"),
                       &out),
            0);  // a folder that is no dataset
  EXPECT_NE(out.find("associations.txt"), std::string::npos) << out;
}

TEST(EvalCliTest, ReconWritesMeanAndHausdorff) {
  testing::TempDir dir;
  PointCloud ref, rec;
  for (int i = 0; i < 50; ++i) {
    for (int j = 0; j < 50; ++j) {
      ref.points.emplace_back(i * 0.01f, j * 0.01f, 0.0f);
      rec.points.emplace_back(i * 0.01f, j * 0.01f, 0.003f);
    }
  }
  ASSERT_TRUE(WritePly(ref, dir.File("ref.ply")).ok());
  ASSERT_TRUE(WritePly(rec, dir.File("rec.ply")).ok());
  std::string out;
  const auto json = RunRecon(dir, "", &out);
  ASSERT_TRUE(json.ok()) << json.status().ToString() << "\n" << out;
  EXPECT_NEAR(json->Get("mean_m")->number(), 0.003, 1e-6);
  EXPECT_NEAR(json->Get("hausdorff_m")->number(), 0.003, 1e-6);
}

// A mesh reference (a dataset's model: one 1 m quad here) is its surface, not its four
// corners: a map 3 mm off the quad reads 3 mm.
TEST(EvalCliTest, ReconTakesAMeshAsItsSurface) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteFileAtomic(dir.File("ref.ply"),
                              "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                              "property float y\nproperty float z\nelement face 1\n"
                              "property list uchar int vertex_indices\nend_header\n"
                              "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
                  .ok());
  PointCloud rec;
  for (int i = 1; i < 20; ++i) {
    for (int j = 1; j < 20; ++j) rec.points.emplace_back(i * 0.05f, j * 0.05f, 0.003f);
  }
  ASSERT_TRUE(WritePly(rec, dir.File("rec.ply")).ok());
  std::string out;
  const auto json = RunRecon(dir, "", &out);
  ASSERT_TRUE(json.ok()) << json.status().ToString() << "\n" << out;
  EXPECT_NEAR(json->Get("mean_m")->number(), 0.003, 1e-4) << out;
  EXPECT_GT(json->Get("reference_points")->number(), 10000);  // sampled every 5 mm
}

// The map is put in the ground truth's frame by the trajectory's whole poses, as the replay
// report does: along a straight path the positions leave any turn about the path open, and a
// map turned 20 degrees about it is off by decimetres at a wall a metre away.
TEST(EvalCliTest, ReconAlignsTheMapByTheTrajectorysWholePoses) {
  testing::TempDir dir;
  Pose A = Pose::Identity();  // the estimate's frame in the ground truth's
  A.linear() = Eigen::AngleAxisd(20 * M_PI / 180, Eigen::Vector3d::UnitX()).toRotationMatrix();
  A.translation() = Eigen::Vector3d(0.1, -0.2, 0.3);
  Trajectory gt, est;
  for (int i = 0; i < 20; ++i) {
    Pose T = Pose::Identity();
    T.translation() = Eigen::Vector3d(0.1 * i, 0, 0);
    gt.push_back({1.0 + 0.1 * i, T});
    est.push_back({1.0 + 0.1 * i, A.inverse() * T});
  }
  PointCloud ref, rec;
  for (int i = 0; i < 40; ++i) {
    for (int j = 0; j < 20; ++j) {
      const Eigen::Vector3d p(0.05 * i, -0.5 + 0.05 * j, 1.0);  // a wall a metre off the path
      ref.points.push_back(p.cast<float>());
      rec.points.push_back((A.inverse() * p).cast<float>());
    }
  }
  ASSERT_TRUE(WriteTumTrajectory(gt, dir.File("gt.txt")).ok());
  ASSERT_TRUE(WriteTumTrajectory(est, dir.File("est.txt")).ok());
  ASSERT_TRUE(WritePly(ref, dir.File("ref.ply")).ok());
  ASSERT_TRUE(WritePly(rec, dir.File("rec.ply")).ok());
  std::string out;
  const auto json = RunRecon(
      dir,
      "--point-to-point --gt-traj " + dir.File("gt.txt") + " --est-traj " + dir.File("est.txt"),
      &out);
  ASSERT_TRUE(json.ok()) << json.status().ToString() << "\n" << out;
  EXPECT_LT(json->Get("mean_m")->number(), 0.001) << out;
}

// A room's corner given as points (no normals), and the same corner moved by a degree and 2 cm:
// --icp places it back and measures it there.
TEST(EvalCliTest, ReconIcpPlacesTheMapOnTheReference) {
  testing::TempDir dir;
  Pose moved = Pose::Identity();
  moved.linear() =
      Eigen::AngleAxisd(M_PI / 180, Eigen::Vector3d(1, 1, 0).normalized()).toRotationMatrix();
  moved.translation() = Eigen::Vector3d(0.02, 0, -0.01);
  PointCloud ref, rec;
  for (int i = 0; i < 60; ++i) {
    for (int j = 0; j < 60; ++j) {
      for (const Eigen::Vector3d& p :
           {Eigen::Vector3d(0.02 * i, 0.02 * j, 0), Eigen::Vector3d(0.02 * i, 0, 0.02 * j),
            Eigen::Vector3d(0, 0.02 * i, 0.02 * j)}) {
        ref.points.push_back(p.cast<float>());
        rec.points.push_back((moved * p).cast<float>());
      }
    }
  }
  ASSERT_TRUE(WritePly(ref, dir.File("ref.ply")).ok());
  ASSERT_TRUE(WritePly(rec, dir.File("rec.ply")).ok());
  std::string out;
  const auto as_it_is = RunRecon(dir, "", &out);
  ASSERT_TRUE(as_it_is.ok()) << out;
  EXPECT_GT(as_it_is->Get("mean_m")->number(), 0.005) << out;
  const auto placed = RunRecon(dir, "--icp", &out);
  ASSERT_TRUE(placed.ok()) << out;
  EXPECT_LT(placed->Get("mean_m")->number(), 0.0005) << out;
  EXPECT_NE(out.find("placed on the reference by ICP: turned 1.0"), std::string::npos) << out;
}

// A straight path at constant speed with one pose pushed 2 cm aside: that pose comes first,
// its neighbours next (1 cm each), and a trajectory of two poses is refused by name.
TEST(EvalCliTest, JumpsListsTheLargestFirst) {
  testing::TempDir dir;
  Trajectory t;
  for (int i = 0; i < 30; ++i) {
    Pose p = Pose::Identity();
    p.translation() = Eigen::Vector3d(0.01 * i, 0, 0);
    if (i == 12) p.translation().y() = 0.02;
    t.push_back({1.0 + i / 30.0, p});
  }
  ASSERT_TRUE(WriteTumTrajectory(t, dir.File("t.txt")).ok());
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_eval") + " jumps --top 3 --traj " + dir.File("t.txt") +
                           " --json " + dir.File("j.json"),
                       &out),
            0)
      << out;
  auto json = ReadJsonFile(dir.File("j.json"));
  ASSERT_TRUE(json.ok());
  const Json* largest = json->Get("largest");
  ASSERT_NE(largest, nullptr);
  ASSERT_EQ(largest->array().size(), 3u);
  EXPECT_EQ(largest->array()[0].Get("index")->number(), 12);
  EXPECT_NEAR(largest->array()[0].Get("deviation_m")->number(), 0.02, 1e-6);
  for (int k : {1, 2}) {
    const int index = static_cast<int>(largest->array()[k].Get("index")->number());
    EXPECT_TRUE(index == 11 || index == 13) << index;
    EXPECT_NEAR(largest->array()[k].Get("deviation_m")->number(), 0.01, 1e-6);
  }
  EXPECT_NEAR(json->Get("deviation_m")->Get("max")->number(), 0.02, 1e-6);
  EXPECT_LT(json->Get("deviation_m")->Get("median")->number(), 1e-6);

  t.resize(2);
  ASSERT_TRUE(WriteTumTrajectory(t, dir.File("short.txt")).ok());
  EXPECT_NE(RunCommand(ProgramPath("ccmd_eval") + " jumps --traj " + dir.File("short.txt"), &out),
            0);
  EXPECT_NE(out.find("at least 3"), std::string::npos) << out;
}

// Two estimates whose errors along z are the same pattern: all of it shared, none apart;
// one estimate alone is refused with what to give.
TEST(EvalCliTest, SharedSplitsTwoEstimatesErrors) {
  testing::TempDir dir;
  Trajectory gt, a, b;
  for (int i = 0; i < 120; ++i) {
    Pose p = Pose::Identity();
    p.translation() = Eigen::Vector3d(std::cos(i * 0.05), std::sin(i * 0.05), 0);
    gt.push_back({1.0 + i / 30.0, p});
    p.translation().z() += (i % 2 ? 0.01 : -0.01);
    a.push_back({1.0 + i / 30.0, p});
    p.translation().x() += 1.5;  // the same error, the estimate elsewhere: alignment removes it
    b.push_back({1.0 + i / 30.0, p});
  }
  ASSERT_TRUE(WriteTumTrajectory(gt, dir.File("gt.txt")).ok());
  ASSERT_TRUE(WriteTumTrajectory(a, dir.File("a.txt")).ok());
  ASSERT_TRUE(WriteTumTrajectory(b, dir.File("b.txt")).ok());
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_eval") + " shared --gt " + dir.File("gt.txt") + " --est " +
                           dir.File("a.txt") + " --est " + dir.File("b.txt") + " --json " +
                           dir.File("s.json"),
                       &out),
            0)
      << out;
  auto json = ReadJsonFile(dir.File("s.json"));
  ASSERT_TRUE(json.ok());
  EXPECT_EQ(json->Get("matched")->number(), 120);
  EXPECT_NEAR(json->Get("shared_rmse_m")->number(), 0.01, 1e-4);
  EXPECT_NEAR(json->Get("apart_rmse_m")->number(), 0, 1e-4);
  EXPECT_NEAR(json->Get("correlation")->number(), 1, 1e-3);
  EXPECT_NE(RunCommand(ProgramPath("ccmd_eval") + " shared --gt " + dir.File("gt.txt") + " --est " +
                           dir.File("a.txt"),
                       &out),
            0);
  EXPECT_NE(out.find("give --est twice"), std::string::npos) << out;
}

}  // namespace
}  // namespace ccmd
