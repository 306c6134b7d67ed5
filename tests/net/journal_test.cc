#include "libccmd/net/journal.h"

#include <sys/stat.h>
#include <unistd.h>

#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/file_util.h"
#include "tests/net/net_test_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

std::uint8_t TypeFor(std::uint64_t seq) { return seq % 3 ? 16 : 17; }

Bytes Message(std::uint64_t i) {
  Bytes m(10 + i * 7);
  for (std::size_t k = 0; k < m.size(); ++k) m[k] = static_cast<std::uint8_t>(i * 31 + k);
  return m;
}

// Writes a journal with records 1..n; returns the offset at which each record starts.
std::vector<std::uint64_t> WriteJournal(const std::string& path, int n) {
  auto writer = JournalWriter::Create(path, {AgentId(3), "robot", nettest::TestCamera()});
  EXPECT_TRUE(writer.ok()) << writer.status().ToString();
  std::vector<std::uint64_t> offsets;
  for (int i = 1; i <= n; ++i) {
    offsets.push_back((*writer)->size());
    EXPECT_TRUE((*writer)->Append(TypeFor(i), i, Message(i)).ok());
  }
  EXPECT_TRUE((*writer)->Sync().ok());
  return offsets;
}

std::uint64_t FileSize(const std::string& path) {
  struct stat st {};
  ::stat(path.c_str(), &st);
  return static_cast<std::uint64_t>(st.st_size);
}

Bytes ReadAll(const std::string& path) {
  std::string s = ReadFileToString(path).value();
  return Bytes(s.begin(), s.end());
}

void WriteAll(const std::string& path, const Bytes& b) {
  std::ofstream(path, std::ios::binary | std::ios::trunc)
      .write(reinterpret_cast<const char*>(b.data()), static_cast<std::streamsize>(b.size()));
}

struct Replayed {
  JournalAgentInfo info;
  std::vector<std::pair<std::uint64_t, Bytes>> records;
};

StatusOr<JournalScan> Replay(const std::string& path, Replayed* out) {
  JournalVisitor v;
  v.on_info = [&](const JournalAgentInfo& info) {
    out->info = info;
    return Status::Ok();
  };
  v.on_record = [&](const JournalRecord& r) {
    EXPECT_EQ(r.type, TypeFor(r.seq));
    out->records.emplace_back(r.seq, Bytes(r.message.begin(), r.message.end()));
    return Status::Ok();
  };
  return ScanJournalFile(path, v);
}

TEST(JournalTest, ReplaysInfoAndRecordsInOrder) {
  testing::TempDir dir;
  const std::string path = dir.File(JournalFileName(AgentId(3)));
  EXPECT_EQ(JournalFileName(AgentId(3)), "agent_00003.journal");
  WriteJournal(path, 6);
  Replayed r;
  StatusOr<JournalScan> scan = Replay(path, &r);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(r.info.id, AgentId(3));
  EXPECT_EQ(r.info.name, "robot");
  EXPECT_EQ(r.info.camera, nettest::TestCamera());
  ASSERT_EQ(r.records.size(), 6u);
  for (int i = 1; i <= 6; ++i) {
    EXPECT_EQ(r.records[i - 1].first, static_cast<std::uint64_t>(i));
    EXPECT_EQ(r.records[i - 1].second, Message(i));
  }
  EXPECT_EQ(scan->valid_bytes, FileSize(path));
  EXPECT_EQ(scan->torn_bytes, 0u);
  EXPECT_EQ(scan->first_seq, 1u);
  EXPECT_EQ(scan->last_seq, 6u);
  // A second journal for the same file is refused: ids and names stay unique.
  EXPECT_FALSE(JournalWriter::Create(path, {AgentId(3), "robot", nettest::TestCamera()}).ok());
}

TEST(JournalTest, TornLastRecordIsCutAtEveryLength) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  const std::vector<std::uint64_t> offsets = WriteJournal(path, 4);
  const Bytes full = ReadAll(path);
  const std::uint64_t last = offsets.back();
  for (std::uint64_t cut = last + 1; cut < full.size(); ++cut) {
    WriteAll(path, Bytes(full.begin(), full.begin() + static_cast<std::ptrdiff_t>(cut)));
    Replayed r;
    StatusOr<JournalScan> scan = Replay(path, &r);
    ASSERT_TRUE(scan.ok()) << "cut at " << cut << ": " << scan.status().ToString();
    EXPECT_EQ(r.records.size(), 3u);
    EXPECT_EQ(scan->valid_bytes, last);
    EXPECT_EQ(scan->torn_bytes, cut - last);
  }
  // Reopening cuts the torn bytes, and appending continues a clean journal.
  auto writer = JournalWriter::OpenForAppend(path, last);
  ASSERT_TRUE(writer.ok());
  EXPECT_EQ(FileSize(path), last);
  ASSERT_TRUE((*writer)->Append(TypeFor(4), 4, Message(4)).ok());
  ASSERT_TRUE((*writer)->Sync().ok());
  Replayed r;
  ASSERT_TRUE(Replay(path, &r).ok());
  ASSERT_EQ(r.records.size(), 4u);
  EXPECT_EQ(r.records[3].second, Message(4));
}

TEST(JournalTest, ZeroFilledTailAndBadLastCrcAreTorn) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  const std::vector<std::uint64_t> offsets = WriteJournal(path, 3);
  Bytes bytes = ReadAll(path);
  const std::size_t size = bytes.size();
  bytes.resize(size + 4096, 0);  // blocks allocated but never written before a power cut
  WriteAll(path, bytes);
  Replayed r;
  StatusOr<JournalScan> scan = Replay(path, &r);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(r.records.size(), 3u);
  EXPECT_EQ(scan->torn_bytes, 4096u);
  EXPECT_EQ(scan->torn_reason, "zero-filled tail");

  bytes.resize(size);
  bytes[size - 1] ^= 0x40;  // the last record's payload half persisted
  WriteAll(path, bytes);
  Replayed r2;
  scan = Replay(path, &r2);
  ASSERT_TRUE(scan.ok());
  EXPECT_EQ(r2.records.size(), 2u);
  EXPECT_EQ(scan->valid_bytes, offsets[2]);
}

TEST(JournalTest, CorruptionBeforeTheLastRecordIsAnError) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  const std::vector<std::uint64_t> offsets = WriteJournal(path, 5);
  const Bytes good = ReadAll(path);

  Bytes payload = good;
  payload[offsets[1] + kFrameHeaderSize + 9] ^= 1;  // inside record 2's message
  WriteAll(path, payload);
  Replayed r;
  StatusOr<JournalScan> scan = Replay(path, &r);
  ASSERT_FALSE(scan.ok());
  EXPECT_EQ(scan.status().code(), StatusCode::kCorrupt);
  EXPECT_NE(scan.status().message().find("offset " + std::to_string(offsets[1])), std::string::npos)
      << scan.status().message();
  EXPECT_EQ(r.records.size(), 1u);  // what came before was delivered in order

  Bytes header = good;
  header[offsets[2]] = 'X';  // magic of record 3
  WriteAll(path, header);
  Replayed r2;
  EXPECT_EQ(Replay(path, &r2).status().code(), StatusCode::kCorrupt);
}

TEST(JournalTest, SequenceNumbersMustIncrease) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  auto writer = JournalWriter::Create(path, {AgentId(1), "a", nettest::TestCamera()});
  ASSERT_TRUE(writer.ok());
  ASSERT_TRUE((*writer)->Append(TypeFor(1), 1, Message(1)).ok());
  ASSERT_TRUE((*writer)->Append(TypeFor(3), 3, Message(3)).ok());  // a gap: allowed, counted
  ASSERT_TRUE((*writer)->Append(TypeFor(2), 2, Message(2)).ok());  // going back: corrupt
  ASSERT_TRUE((*writer)->Append(TypeFor(4), 4, Message(4)).ok());
  Replayed r;
  StatusOr<JournalScan> scan = Replay(path, &r);
  EXPECT_EQ(scan.status().code(), StatusCode::kCorrupt);
  ASSERT_EQ(r.records.size(), 2u);
  EXPECT_EQ(r.records[1].first, 3u);
}

TEST(JournalTest, TornInfoRecordMeansNothingWasStored) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  WriteJournal(path, 0);
  Bytes bytes = ReadAll(path);
  bytes.resize(bytes.size() / 2);
  WriteAll(path, bytes);
  StatusOr<JournalScan> scan = ScanJournalFile(path);
  ASSERT_TRUE(scan.ok());
  EXPECT_FALSE(scan->has_info);
  EXPECT_EQ(scan->valid_bytes, 0u);
}

TEST(JournalTest, RollBackCutsUnsyncedRecords) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  auto writer = JournalWriter::Create(path, {AgentId(1), "a", nettest::TestCamera()});
  ASSERT_TRUE(writer.ok());
  ASSERT_TRUE((*writer)->Append(TypeFor(1), 1, Message(1)).ok());
  ASSERT_TRUE((*writer)->Sync().ok());
  ASSERT_TRUE((*writer)->Append(TypeFor(2), 2, Message(2)).ok());
  ASSERT_TRUE((*writer)->RollBack().ok());
  Replayed r;
  ASSERT_TRUE(Replay(path, &r).ok());
  EXPECT_EQ(r.records.size(), 1u);
}

// The info record's layout before distortion existed (u16 id, u8 name length, name, 4 x f64,
// 2 x u32, f64), byte by byte: journals written then still resume, with no distortion.
TEST(JournalTest, InfoRecordWithoutDistortionIsTheOriginalLayout) {
  JournalAgentInfo info{AgentId(4), "icl", nettest::TestCamera()};
  info.camera.fy = -480.0;  // refused before; a valid camera now
  Bytes old = {4, 0, 3, 'i', 'c', 'l'};
  for (double v : {info.camera.fx, info.camera.fy, info.camera.cx, info.camera.cy}) {
    std::uint64_t bits;
    std::memcpy(&bits, &v, 8);
    for (int i = 0; i < 8; ++i) old.push_back(static_cast<std::uint8_t>(bits >> (8 * i)));
  }
  for (std::uint32_t v : {info.camera.width, info.camera.height}) {
    for (int i = 0; i < 4; ++i) old.push_back(static_cast<std::uint8_t>(v >> (8 * i)));
  }
  std::uint64_t bits;
  std::memcpy(&bits, &info.camera.depth_scale, 8);
  for (int i = 0; i < 8; ++i) old.push_back(static_cast<std::uint8_t>(bits >> (8 * i)));
  EXPECT_EQ(SerializeJournalInfo(info), old);
  StatusOr<JournalAgentInfo> parsed = ParseJournalInfo(old);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, info.camera);
}

TEST(JournalTest, InfoRecordCarriesDistortion) {
  JournalAgentInfo info{AgentId(2), "fr1", nettest::TestCamera()};
  info.camera.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  Bytes bytes = SerializeJournalInfo(info);
  JournalAgentInfo plain = info;
  plain.camera.distortion = {0, 0, 0, 0, 0};
  EXPECT_EQ(bytes.size(), SerializeJournalInfo(plain).size() + 1 + 40);
  StatusOr<JournalAgentInfo> parsed = ParseJournalInfo(bytes);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, info.camera);
  // What a later format might add is refused clearly, not misread.
  bytes[SerializeJournalInfo(plain).size()] = 9;
  const auto unknown = ParseJournalInfo(bytes);
  ASSERT_FALSE(unknown.ok());
  EXPECT_NE(unknown.status().message().find("camera extension"), std::string::npos);
  bytes.resize(SerializeJournalInfo(plain).size() + 1 + 20);  // cut inside the coefficients
  EXPECT_FALSE(ParseJournalInfo(bytes).ok());
}

}  // namespace
}  // namespace ccmd
