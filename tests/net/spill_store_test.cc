#include "libccmd/net/spill_store.h"

#include <dirent.h>

#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

int CountSegments(const std::string& dir) {
  int n = 0;
  DIR* d = ::opendir(dir.c_str());
  while (dirent* e = ::readdir(d)) {
    if (std::string(e->d_name).find(".spill") != std::string::npos) ++n;
  }
  ::closedir(d);
  return n;
}

Bytes Message(int i) { return Bytes(100 + i, static_cast<std::uint8_t>(i)); }

TEST(SpillStoreTest, FifoAcrossSegmentsAndFilesRemoved) {
  testing::TempDir dir;
  auto store = SpillStore::Open(dir.File("spill"), 1 << 20, /*segment_bytes=*/1000);
  ASSERT_TRUE(store.ok()) << store.status().ToString();
  for (int i = 1; i <= 40; ++i) ASSERT_TRUE((*store)->Push(16, i, Message(i)).ok());
  EXPECT_EQ((*store)->count(), 40u);
  EXPECT_GT(CountSegments(dir.File("spill")), 3);
  for (int i = 1; i <= 40; ++i) {
    ASSERT_FALSE((*store)->empty());
    EXPECT_EQ((*store)->front_message_bytes(), Message(i).size());
    StatusOr<SpilledMessage> m = (*store)->Pop();
    ASSERT_TRUE(m.ok()) << m.status().ToString();
    EXPECT_EQ(m->seq, static_cast<std::uint64_t>(i));
    EXPECT_EQ(m->type, 16);
    EXPECT_EQ(m->message, Message(i));
    if (i == 20) {
      ASSERT_TRUE((*store)->Push(17, 41, Message(41)).ok());  // interleaved
    }
  }
  StatusOr<SpilledMessage> last = (*store)->Pop();
  ASSERT_TRUE(last.ok());
  EXPECT_EQ(last->seq, 41u);
  EXPECT_TRUE((*store)->empty());
  EXPECT_EQ((*store)->disk_bytes(), 0u);
  EXPECT_EQ(CountSegments(dir.File("spill")), 0);
}

TEST(SpillStoreTest, DiskLimitAndExclusiveFolder) {
  testing::TempDir dir;
  auto store = SpillStore::Open(dir.File("spill"), /*max_bytes=*/1000, 400);
  ASSERT_TRUE(store.ok());
  int pushed = 0;
  Status s;
  while ((s = (*store)->Push(16, pushed + 1, Message(0))).ok()) ++pushed;
  EXPECT_EQ(s.code(), StatusCode::kOutOfRange);
  // Each record is 20 + 8 + 100 bytes: 7 fit in 1000.
  EXPECT_EQ(pushed, 7);
  EXPECT_EQ((*store)->disk_bytes(), 7u * 128);
  EXPECT_EQ(SpillStore::Open(dir.File("spill"), 1000).status().code(), StatusCode::kUnavailable);
}

TEST(SpillStoreTest, LeftoversOfAnEarlierProcessAreCleared) {
  testing::TempDir dir;
  ASSERT_TRUE(MakeDirectories(dir.File("spill")).ok());
  ASSERT_TRUE(WriteFileAtomic(dir.File("spill/segment_00000007.spill"), "old bytes").ok());
  ASSERT_TRUE(WriteFileAtomic(dir.File("spill/notes.txt"), "not ours").ok());
  auto store = SpillStore::Open(dir.File("spill"), 1 << 20);
  ASSERT_TRUE(store.ok());
  EXPECT_EQ(CountSegments(dir.File("spill")), 0);
  EXPECT_TRUE(FileExists(dir.File("spill/notes.txt")));
}

}  // namespace
}  // namespace ccmd
