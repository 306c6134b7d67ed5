#include "libccmd/net/journal.h"

#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/file_util.h"
#include "proto/crc32c.h"
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

TEST(JournalTest, ZeroFilledTailAndNeverWrittenBlocksAreTorn) {
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

  // A last record spanning blocks whose last whole block was never written: its length is
  // all there, but its end reads as zeros.
  auto writer = JournalWriter::OpenForAppend(path, size);
  ASSERT_TRUE(writer.ok());
  const std::uint64_t start = (*writer)->size();
  ASSERT_TRUE((*writer)->Append(TypeFor(4), 4, Bytes(3 * 4096, 0x5A)).ok());
  writer->reset();
  bytes = ReadAll(path);
  const std::size_t block = (start + kFrameHeaderSize + 4096 + 4095) / 4096 * 4096;
  std::fill(bytes.begin() + static_cast<std::ptrdiff_t>(block), bytes.end(), 0);
  ASSERT_GE(bytes.size() - block, 4096u);
  WriteAll(path, bytes);
  Replayed r2;
  scan = Replay(path, &r2);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(r2.records.size(), 3u);
  EXPECT_EQ(scan->valid_bytes, start);
  EXPECT_GT(start, offsets[2]);
}

TEST(JournalTest, ACompleteLastRecordFailingItsCrcIsDamageNotATornWrite) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  const std::vector<std::uint64_t> offsets = WriteJournal(path, 3);
  Bytes bytes = ReadAll(path);
  bytes.back() ^= 0x40;  // one bit of a record that was written in full
  WriteAll(path, bytes);
  Replayed r;
  StatusOr<JournalScan> scan = Replay(path, &r);
  ASSERT_EQ(scan.status().code(), StatusCode::kCorrupt);
  const std::string text = scan.status().message();
  // Nothing after it passes its checks, so the advice is a cut exactly there.
  EXPECT_NE(text.find("nothing after it passes"), std::string::npos) << text;
  EXPECT_NE(text.find("truncate -s " + std::to_string(offsets[2])), std::string::npos) << text;
  EXPECT_EQ(r.records.size(), 2u);
}

TEST(JournalTest, DamageAdviceNeverCutsAwayIntactRecords) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00001.journal");
  const std::vector<std::uint64_t> offsets = WriteJournal(path, 5);
  Bytes bytes = ReadAll(path);
  bytes[offsets[1] + kFrameHeaderSize + 9] ^= 1;  // inside record 2's message
  WriteAll(path, bytes);
  Replayed r;
  StatusOr<JournalScan> scan = Replay(path, &r);
  ASSERT_EQ(scan.status().code(), StatusCode::kCorrupt);
  const std::string text = scan.status().message();
  EXPECT_NE(text.find("3 intact record(s) follow it (sequence numbers 3..5)"), std::string::npos)
      << text;
  EXPECT_EQ(text.find("truncate"), std::string::npos) << text;
}

// Writes a journal with records of `message_bytes` under a limit of `limit`.
void WriteLargeRecords(const std::string& path, std::uint32_t limit, std::size_t message_bytes) {
  JournalAgentInfo info{AgentId(2), "big", nettest::TestCamera()};
  info.max_payload_bytes = limit;
  auto writer = JournalWriter::Create(path, info);
  ASSERT_TRUE(writer.ok()) << writer.status().ToString();
  for (int i = 1; i <= 3; ++i) {
    ASSERT_TRUE((*writer)->Append(16, i, Bytes(message_bytes, static_cast<std::uint8_t>(i))).ok());
  }
  ASSERT_TRUE((*writer)->Sync().ok());
}

TEST(JournalTest, RecordsAreReadWithTheLimitTheJournalWasWrittenWith) {
  testing::TempDir dir;
  const std::string path = dir.File("agent_00002.journal");
  WriteLargeRecords(path, 64 << 10, 40 << 10);
  // Whatever limit the reader runs with now, the journal's own applies.
  StatusOr<JournalScan> scan = ScanJournalFile(path);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(scan->records, 3u);
  EXPECT_EQ(scan->info.max_payload_bytes, 64u << 10);

  // Records above the recorded limit cannot have been written by the server: damage.
  testing::TempDir dir2;
  const std::string small = dir2.File("agent_00002.journal");
  WriteLargeRecords(small, 16 << 10, 40 << 10);
  EXPECT_EQ(ScanJournalFile(small).status().code(), StatusCode::kCorrupt);

  // An update record raises the limit for the records after it.
  auto writer = JournalWriter::OpenForAppend(path, FileSize(path));
  ASSERT_TRUE(writer.ok());
  ASSERT_TRUE((*writer)->AppendUpdate({1 << 20, {}}).ok());
  ASSERT_TRUE((*writer)->Append(16, 4, Bytes(200 << 10, 4)).ok());
  ASSERT_TRUE((*writer)->Sync().ok());
  scan = ScanJournalFile(path);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(scan->records, 4u);
  EXPECT_EQ(scan->info.max_payload_bytes, 1u << 20);
}

TEST(JournalTest, JournalsOfProtocolVersion1StayReadable) {
  // Version 1: frames with version byte 1, an info record without limit and verifier.
  auto v1 = [](std::uint8_t type, const Bytes& payload) {
    Bytes frame = EncodeFrame(type, 0, payload);
    frame[4] = 1;
    const std::uint32_t crc = Crc32c(frame.data(), 16);
    for (int i = 0; i < 4; ++i) frame[16 + i] = static_cast<std::uint8_t>(crc >> (8 * i));
    return frame;
  };
  Bytes info = SerializeJournalInfo({AgentId(4), "old", nettest::TestCamera()});
  info.resize(info.size() - 4 - kIdentitySize);
  Bytes journal = v1(kJournalInfoRecord, info);
  for (std::uint64_t seq = 1; seq <= 2; ++seq) {
    Bytes data(8, 0);
    data[0] = static_cast<std::uint8_t>(seq);
    const Bytes m = Message(seq);
    data.insert(data.end(), m.begin(), m.end());
    const Bytes frame = v1(16, data);
    journal.insert(journal.end(), frame.begin(), frame.end());
  }
  StatusOr<JournalScan> scan = ScanJournalBytes(journal);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(scan->records, 2u);
  EXPECT_EQ(scan->info.name, "old");
  EXPECT_EQ(scan->info.max_payload_bytes, 0u);  // not recorded
  EXPECT_TRUE(IsZero(scan->info.verifier));
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
// 2 x u32, f64), byte by byte: version 2 appends the limit and the verifier to it, and
// version 1 journals written then still resume, with no distortion.
TEST(JournalTest, InfoRecordWithoutDistortionExtendsTheOriginalLayout) {
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
  const Bytes v2 = SerializeJournalInfo(info);
  ASSERT_EQ(v2.size(), old.size() + 4 + kIdentitySize);
  EXPECT_TRUE(std::equal(old.begin(), old.end(), v2.begin()));
  StatusOr<JournalAgentInfo> parsed = ParseJournalInfo(old, 1);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, info.camera);
  EXPECT_EQ(parsed->max_payload_bytes, 0u);
  EXPECT_FALSE(ParseJournalInfo(old).ok());  // a version 2 record needs the limit
}

// A version 1 journal of a distorted camera (the trailer right after the camera) resumes.
TEST(JournalTest, VersionOneInfoRecordWithDistortion) {
  JournalAgentInfo info{AgentId(2), "fr1", nettest::TestCamera()};
  info.camera.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  Bytes v2 = SerializeJournalInfo(info);
  // Version 1 had no limit and verifier between the camera and the trailer.
  const std::size_t camera_end = 2 + 1 + info.name.size() + 48;
  Bytes v1(v2.begin(), v2.begin() + camera_end);
  v1.insert(v1.end(), v2.begin() + camera_end + 4 + kIdentitySize, v2.end());
  StatusOr<JournalAgentInfo> parsed = ParseJournalInfo(v1, 1);
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

// A resumed server weighs the agent's depths as the live one did: the depth noise is a second
// trailer (byte 2, sigma0, sigma2), after the distortion's when there is one.
TEST(JournalTest, InfoRecordCarriesTheTrajectoryCamera) {
  JournalAgentInfo info{AgentId(3), "kitchen", nettest::TestCamera()};
  const std::size_t base = SerializeJournalInfo(info).size();
  info.camera.depth_sigma0 = 0.0005;
  info.camera.trajectory_t = {-0.025, 0, 0};
  Bytes bytes = SerializeJournalInfo(info);
  ASSERT_EQ(bytes.size(), base + 1 + 16 + 1 + 56);
  EXPECT_EQ(bytes[base], 2);
  EXPECT_EQ(bytes[base + 17], 3);
  StatusOr<JournalAgentInfo> parsed = ParseJournalInfo(bytes);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, info.camera);

  // The trailer stating the colour camera itself is damage (a writer leaves it out).
  Bytes identity(bytes.begin(), bytes.begin() + base + 18);
  identity.resize(identity.size() + 6 * 8, 0);
  std::uint64_t one;  // qw = 1.0, little-endian as every f64 of the format
  const double w = 1.0;
  std::memcpy(&one, &w, 8);
  for (int i = 0; i < 8; ++i) identity.push_back(static_cast<std::uint8_t>(one >> (8 * i)));
  ASSERT_EQ(identity.size(), bytes.size());
  EXPECT_EQ(ParseJournalInfo(identity).status().code(), StatusCode::kCorrupt);
}

TEST(JournalTest, InfoRecordCarriesTheDepthNoise) {
  JournalAgentInfo info{AgentId(2), "icl", nettest::TestCamera()};
  info.camera.depth_sigma0 = 0.0005;
  JournalAgentInfo plain = info;
  plain.camera.depth_sigma0 = 0;
  const std::size_t base = SerializeJournalInfo(plain).size();
  Bytes bytes = SerializeJournalInfo(info);
  ASSERT_EQ(bytes.size(), base + 1 + 16);
  EXPECT_EQ(bytes[base], 2);
  StatusOr<JournalAgentInfo> parsed = ParseJournalInfo(bytes);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, info.camera);

  info.camera.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  info.camera.depth_sigma2 = 0.0015;
  bytes = SerializeJournalInfo(info);
  ASSERT_EQ(bytes.size(), base + 1 + 40 + 1 + 16);
  EXPECT_EQ(bytes[base], 1);
  EXPECT_EQ(bytes[base + 41], 2);
  parsed = ParseJournalInfo(bytes);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, info.camera);

  // Trailers out of order, twice, or zero noise are damage.
  Bytes swapped(bytes.begin(), bytes.begin() + base);
  swapped.insert(swapped.end(), bytes.begin() + base + 41, bytes.end());
  swapped.insert(swapped.end(), bytes.begin() + base, bytes.begin() + base + 41);
  EXPECT_EQ(ParseJournalInfo(swapped).status().code(), StatusCode::kCorrupt);
  Bytes twice = bytes;
  twice.insert(twice.end(), bytes.begin() + base + 41, bytes.end());
  EXPECT_EQ(ParseJournalInfo(twice).status().code(), StatusCode::kCorrupt);
  Bytes zero(bytes.begin(), bytes.begin() + base + 42);
  zero.resize(zero.size() + 16, 0);
  EXPECT_EQ(ParseJournalInfo(zero).status().code(), StatusCode::kCorrupt);
}

}  // namespace
}  // namespace ccmd
