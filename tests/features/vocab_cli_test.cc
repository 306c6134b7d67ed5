// ccmd_vocab end to end: training from each kind of input, the saved file, --info, errors.

#include <gtest/gtest.h>

#include <cstdio>
#include <fstream>

#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/string_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

std::string Vocab() { return testing::ProgramPath("ccmd_vocab"); }

// A rendered sequence of `frames` 320x240 frames in the TUM layout.
Status WriteSmallSequence(const std::string& folder, int frames) {
  SyntheticSequenceOptions options;
  options.frames = frames;
  options.width = 320;
  options.height = 240;
  options.threads = 1;
  return WriteSyntheticSequence(folder, options).status();
}

TEST(VocabCliTest, TrainsFromASyntheticSpec) {
  testing::TempDir dir;
  std::string out;
  ASSERT_EQ(testing::RunCommand(Vocab() + " --out " + dir.File("v.bin") +
                                    " --synth frames=24,seed=3,step=6 --k 5 --depth 2"
                                    " --features 300 --threads 1 --json " +
                                    dir.File("v.json"),
                                &out),
            0)
      << out;
  auto v = Vocabulary::Load(dir.File("v.bin"));
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  EXPECT_EQ(v->branching(), 5);
  EXPECT_EQ(v->depth(), 2);
  EXPECT_EQ(v->training_images(), 4);  // frames 0, 6, 12, 18
  auto json = ReadJsonFile(dir.File("v.json"));
  ASSERT_TRUE(json.ok());
  EXPECT_EQ(json->Get("words")->number(), v->word_count());
  EXPECT_EQ(json->Get("images")->number(), 4);
  EXPECT_LE(json->Get("descriptors")->number(), 4 * 300);

  ASSERT_EQ(testing::RunCommand(Vocab() + " --info " + dir.File("v.bin"), &out), 0) << out;
  EXPECT_NE(out.find("k=5 L=2"), std::string::npos) << out;
  EXPECT_NE(out.find(std::to_string(v->word_count()) + " words"), std::string::npos) << out;
}

TEST(VocabCliTest, TrainsFromDatasetsAndImageFolders) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteSmallSequence(dir.File("seq"), 5).ok());
  std::string out;
  ASSERT_EQ(testing::RunCommand(Vocab() + " --out " + dir.File("v.bin") + " --dataset " +
                                    dir.File("seq") + " --images " + dir.File("seq/rgb") +
                                    " --k 4 --depth 2 --features 200 --json " + dir.File("v.json"),
                                &out),
            0)
      << out;
  auto json = ReadJsonFile(dir.File("v.json"));
  ASSERT_TRUE(json.ok());
  EXPECT_EQ(json->Get("images")->number(), 10);  // five from rgb.txt, five from the folder
  EXPECT_TRUE(Vocabulary::Load(dir.File("v.bin")).ok());
}

TEST(VocabCliTest, TrainsFromASevenScenesSequenceAsUnpacked) {
  // The colour images of frame-XXXXXX.color.png, not the depth PNGs beside them.
  testing::TempDir dir;
  ASSERT_TRUE(WriteSmallSequence(dir.File("seq"), 4).ok());
  auto list = ReadFileToString(dir.File("seq/rgb.txt"));
  ASSERT_TRUE(list.ok());
  ASSERT_TRUE(MakeDirectories(dir.File("seq-01")).ok());
  int i = 0;
  for (const std::string& line : Split(*list, '\n')) {
    const auto fields = SplitWhitespace(line);
    if (fields.size() < 2 || fields[0].front() == '#') continue;
    char stem[32];
    std::snprintf(stem, sizeof(stem), "/frame-%06d.", i++);
    auto colour = ReadFileToString(dir.File("seq/" + std::string(fields[1])));
    ASSERT_TRUE(colour.ok());
    ASSERT_TRUE(WriteFileAtomic(dir.File("seq-01") + stem + "color.png", *colour).ok());
    ASSERT_TRUE(WriteFileAtomic(dir.File("seq-01") + stem + "depth.png", "").ok());
  }
  ASSERT_EQ(i, 4);
  std::string out;
  ASSERT_EQ(testing::RunCommand(Vocab() + " --out " + dir.File("v.bin") + " --dataset " +
                                    dir.File("seq-01") + " --k 4 --depth 2 --features 200 --json " +
                                    dir.File("v.json"),
                                &out),
            0)
      << out;
  auto json = ReadJsonFile(dir.File("v.json"));
  ASSERT_TRUE(json.ok());
  EXPECT_EQ(json->Get("images")->number(), 4);
}

TEST(VocabCliTest, ErrorsAreReported) {
  testing::TempDir dir;
  std::string out;
  EXPECT_NE(testing::RunCommand(Vocab() + " --out " + dir.File("v.bin"), &out), 0);
  EXPECT_NE(out.find("no training data"), std::string::npos) << out;
  EXPECT_NE(
      testing::RunCommand(
          Vocab() + " --out " + dir.File("v.bin") + " --dataset " + dir.File("missing"), &out),
      0);
  EXPECT_NE(
      testing::RunCommand(Vocab() + " --out " + dir.File("v.bin") + " --synth frames=x", &out), 0);
  {
    std::ofstream bad(dir.File("bad.bin"));
    bad << "CCMDVOC definitely not a vocabulary, just text padding the header out";
  }
  EXPECT_NE(testing::RunCommand(Vocab() + " --info " + dir.File("bad.bin"), &out), 0);
  EXPECT_NE(out.find("corrupt"), std::string::npos) << out;
  EXPECT_FALSE(FileExists(dir.File("v.bin")));
}

}  // namespace
}  // namespace ccmd
