#include <gtest/gtest.h>

#include "libccmd/io/tum_dataset.h"
#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(SynthCliTest, WritesAReadableSequence) {
  testing::TempDir dir;
  std::string out;
  ASSERT_EQ(testing::RunCommand(testing::ProgramPath("ccmd_synth") + " --out " + dir.File("seq") +
                                    " --frames 5 --width 160 --height 120 --seed 9",
                                &out),
            0)
      << out;
  for (const char* f : {"rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "surface.ply"}) {
    EXPECT_TRUE(FileExists(dir.File("seq/") + f)) << f;
  }
  auto seq = TumSequence::Open(dir.File("seq"), std::nullopt);
  ASSERT_TRUE(seq.ok());
  EXPECT_EQ(seq->size(), 5u);
}

TEST(SynthCliTest, BadArgumentsFailWithAMessage) {
  std::string out;
  EXPECT_NE(testing::RunCommand(testing::ProgramPath("ccmd_synth") + " --frames 5", &out), 0);
  EXPECT_NE(out.find("--out"), std::string::npos) << out;
  EXPECT_NE(
      testing::RunCommand(testing::ProgramPath("ccmd_synth") + " --out /tmp/x --width 5", &out), 0);
}

}  // namespace
}  // namespace ccmd
