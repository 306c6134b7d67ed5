#include "libccmd/net/journal.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <optional>

#include "proto/crc32c.h"
#include "proto/frame.h"

namespace ccmd {
namespace {

// Optional trailers of the info record, each a byte and its fields, in this order: the
// camera's 5 distortion coefficients; its depth noise (sigma0, sigma2); its trajectory camera
// (translation, quaternion).
constexpr std::uint8_t kJournalCameraDistortion = 1;
constexpr std::uint8_t kJournalCameraDepthNoise = 2;
constexpr std::uint8_t kJournalCameraTrajectory = 3;

std::string Errno(const std::string& what) { return what + ": " + std::strerror(errno); }

Status WriteAll(int fd, const std::uint8_t* data, std::size_t size, const std::string& path) {
  while (size > 0) {
    const ssize_t n = ::write(fd, data, size);
    if (n < 0) {
      if (errno == EINTR) continue;
      return IoError(Errno("writing " + path));
    }
    data += n;
    size -= static_cast<std::size_t>(n);
  }
  return Status::Ok();
}

// Random access to the bytes being scanned: a file (pread) or memory.
class ScanSource {
 public:
  virtual ~ScanSource() = default;
  virtual std::uint64_t size() const = 0;
  virtual Status Read(std::uint64_t offset, std::size_t n, std::uint8_t* out) = 0;
};

class MemorySource : public ScanSource {
 public:
  explicit MemorySource(ByteSpan bytes) : bytes_(bytes) {}
  std::uint64_t size() const override { return bytes_.size(); }
  Status Read(std::uint64_t offset, std::size_t n, std::uint8_t* out) override {
    std::memcpy(out, bytes_.data() + offset, n);
    return Status::Ok();
  }

 private:
  ByteSpan bytes_;
};

class FileSource : public ScanSource {
 public:
  FileSource(int fd, std::uint64_t size, std::string path)
      : fd_(fd), size_(size), path_(std::move(path)) {}
  std::uint64_t size() const override { return size_; }
  Status Read(std::uint64_t offset, std::size_t n, std::uint8_t* out) override {
    while (n > 0) {
      const ssize_t got = ::pread(fd_, out, n, static_cast<off_t>(offset));
      if (got < 0) {
        if (errno == EINTR) continue;
        return IoError(Errno("reading " + path_));
      }
      if (got == 0) return IoError("reading " + path_ + ": file shrank during replay");
      out += got;
      offset += static_cast<std::uint64_t>(got);
      n -= static_cast<std::size_t>(got);
    }
    return Status::Ok();
  }

 private:
  int fd_;
  std::uint64_t size_;
  std::string path_;
};

StatusOr<bool> AllZeroFrom(ScanSource* src, std::uint64_t offset) {
  std::uint8_t chunk[4096];
  while (offset < src->size()) {
    const std::size_t n =
        static_cast<std::size_t>(std::min<std::uint64_t>(sizeof(chunk), src->size() - offset));
    CCMD_RETURN_IF_ERROR(src->Read(offset, n, chunk));
    for (std::size_t i = 0; i < n; ++i) {
      if (chunk[i] != 0) return false;
    }
    offset += n;
  }
  return true;
}

// File-system blocks allocated but never written read as zeros. A last record whose file
// ends in at least one whole such block (at or after `from`) was shown incomplete.
constexpr std::uint64_t kFileBlock = 4096;
bool EndsInUnwrittenBlock(const std::vector<std::uint8_t>& payload, std::uint64_t payload_offset) {
  std::size_t last_nonzero = payload.size();
  while (last_nonzero > 0 && payload[last_nonzero - 1] == 0) --last_nonzero;
  const std::uint64_t zeros_from = payload_offset + last_nonzero;
  const std::uint64_t block = (zeros_from + kFileBlock - 1) / kFileBlock * kFileBlock;
  return block + kFileBlock <= payload_offset + payload.size();
}

// A record that passes every frame check (header, length within the file, payload CRC).
struct IntactRecord {
  std::uint64_t end = 0;
  std::uint8_t type = 0;
  std::uint64_t seq = 0;  // data records only
};

std::optional<IntactRecord> IntactAt(ScanSource* src, std::uint64_t pos,
                                     std::vector<std::uint8_t>* payload) {
  std::uint8_t header_bytes[kFrameHeaderSize];
  if (src->size() - pos < kFrameHeaderSize) return std::nullopt;
  if (!src->Read(pos, kFrameHeaderSize, header_bytes).ok()) return std::nullopt;
  StatusOr<FrameHeader> h = ParseFrameHeader(
      ByteSpan(header_bytes, kFrameHeaderSize),
      FrameLimits{.max_payload_bytes = kMaxJournalPayloadBytes, .oldest_version = 1});
  if (!h.ok() || h->tagged() || h->payload_size > src->size() - pos - kFrameHeaderSize) {
    return std::nullopt;
  }
  payload->resize(h->payload_size);
  if (!payload->empty() &&
      !src->Read(pos + kFrameHeaderSize, payload->size(), payload->data()).ok()) {
    return std::nullopt;
  }
  if (Crc32c(*payload) != h->payload_crc) return std::nullopt;
  IntactRecord r{pos + kFrameHeaderSize + h->payload_size, h->type, 0};
  if (IsKnownDataType(h->type)) {
    StatusOr<DataEnvelope> env = ParseDataEnvelope(*payload);
    if (env.ok()) r.seq = env->seq;
  }
  return r;
}

// After damage at `pos`: the records further on that pass their checks, found by searching
// for the frame magic. Decides what the error may advise.
struct IntactAfter {
  std::uint64_t records = 0;
  std::uint64_t first_seq = 0, last_seq = 0;
};

StatusOr<IntactAfter> FindIntactAfter(ScanSource* src, std::uint64_t pos) {
  IntactAfter found;
  std::vector<std::uint8_t> chunk(
      static_cast<std::size_t>(std::min<std::uint64_t>(1 << 20, src->size() - pos))),
      payload;
  std::uint64_t at = pos + 1;
  while (at + kFrameHeaderSize <= src->size()) {
    const std::size_t n =
        static_cast<std::size_t>(std::min<std::uint64_t>(chunk.size(), src->size() - at));
    CCMD_RETURN_IF_ERROR(src->Read(at, n, chunk.data()));
    std::uint64_t next = at + n - (sizeof(kFrameMagic) - 1);  // magic split across chunks
    for (std::size_t i = 0; i + sizeof(kFrameMagic) <= n; ++i) {
      if (std::memcmp(chunk.data() + i, kFrameMagic, sizeof(kFrameMagic)) != 0) continue;
      std::optional<IntactRecord> r = IntactAt(src, at + i, &payload);
      if (!r) continue;
      ++found.records;
      if (r->seq != 0) {
        if (found.first_seq == 0) found.first_seq = r->seq;
        found.last_seq = r->seq;
      }
      next = r->end;  // continue after it
      break;
    }
    if (next <= at) next = at + 1;
    at = next;
  }
  return found;
}

class Scanner {
 public:
  Scanner(ScanSource* src, std::string name, const JournalVisitor& visitor,
          const JournalScanOptions& options)
      : src_(src), name_(std::move(name)), visitor_(visitor), options_(options) {}

  StatusOr<JournalScan> Run() {
    while (pos_ < src_->size()) {
      CCMD_ASSIGN_OR_RETURN(const bool done, Next());
      if (done) return scan_;
    }
    scan_.valid_bytes = pos_;
    return scan_;
  }

 private:
  // Reads the record at pos_; true when the scan ends here (a torn tail).
  StatusOr<bool> Next() {
    const std::uint64_t left = src_->size() - pos_;
    if (left < kFrameHeaderSize) {
      CCMD_ASSIGN_OR_RETURN(const bool zeros, AllZeroFrom(src_, pos_));
      return Torn(zeros ? "zero-filled tail" : "incomplete record header");
    }
    std::uint8_t header_bytes[kFrameHeaderSize];
    CCMD_RETURN_IF_ERROR(src_->Read(pos_, kFrameHeaderSize, header_bytes));
    StatusOr<FrameHeader> header = ParseFrameHeader(
        ByteSpan(header_bytes, kFrameHeaderSize),
        FrameLimits{.max_payload_bytes = kMaxJournalPayloadBytes, .oldest_version = 1});
    if (!header.ok()) {
      CCMD_ASSIGN_OR_RETURN(const bool zeros, AllZeroFrom(src_, pos_));
      if (zeros) return Torn("zero-filled tail");
      return Damaged("bad record header (" + header.status().message() + ")");
    }
    if (header->tagged()) return Damaged("record with a tag (journals hold untagged records)");
    const std::uint32_t limit = Limit(header->type);
    if (header->payload_size > limit) {
      return Damaged("record of " + std::to_string(header->payload_size) +
                     " bytes, above the limit of " + std::to_string(limit) +
                     " this journal was written with");
    }
    const std::uint64_t end = pos_ + kFrameHeaderSize + header->payload_size;
    if (end > src_->size()) {
      return Torn("incomplete record (the file ends " + std::to_string(left - kFrameHeaderSize) +
                  " bytes into a payload of " + std::to_string(header->payload_size) + ")");
    }
    payload_.resize(header->payload_size);
    if (!payload_.empty()) {
      CCMD_RETURN_IF_ERROR(src_->Read(pos_ + kFrameHeaderSize, payload_.size(), payload_.data()));
    }
    if (Crc32c(payload_) != header->payload_crc) {
      if (end == src_->size() && EndsInUnwrittenBlock(payload_, pos_ + kFrameHeaderSize)) {
        return Torn("the last record ends in never-written (zero) blocks");
      }
      return Damaged("record payload CRC mismatch");
    }
    CCMD_RETURN_IF_ERROR(Record(header->type, header->version));
    pos_ = end;
    return false;
  }

  std::uint32_t Limit(std::uint8_t type) const {
    if (!scan_.has_info || type == kJournalUpdateRecord) return kMaxJournalInfoBytes;
    const std::uint32_t recorded =
        scan_.info.max_payload_bytes != 0 ? scan_.info.max_payload_bytes : kMaxJournalPayloadBytes;
    return std::min(recorded, options_.max_payload_bytes);
  }

  Status Record(std::uint8_t type, std::uint8_t version) {
    if (!scan_.has_info) {
      if (type != kJournalInfoRecord)
        return Damaged("first record is not a journal info record").status();
      StatusOr<JournalAgentInfo> info = ParseJournalInfo(payload_, version);
      if (!info.ok()) return Damaged(info.status().message()).status();
      scan_.info = std::move(*info);
      scan_.has_info = true;
      if (visitor_.on_info) CCMD_RETURN_IF_ERROR(visitor_.on_info(scan_.info));
      return Status::Ok();
    }
    if (type == kJournalUpdateRecord) {
      StatusOr<JournalUpdate> update = ParseJournalUpdate(payload_);
      if (!update.ok()) return Damaged(update.status().message()).status();
      scan_.info.max_payload_bytes = update->max_payload_bytes;
      if (!IsZero(update->verifier)) scan_.info.verifier = update->verifier;
      return Status::Ok();
    }
    if (!IsKnownDataType(type)) {
      return Damaged("record of unknown type " + std::to_string(type)).status();
    }
    StatusOr<DataEnvelope> env = ParseDataEnvelope(payload_);
    if (!env.ok()) return Damaged(env.status().message()).status();
    if (env->seq <= scan_.last_seq) {
      return Damaged("sequence number " + std::to_string(env->seq) + " does not increase").status();
    }
    if (scan_.last_seq != 0 && env->seq != scan_.last_seq + 1) ++scan_.gaps;
    if (scan_.records == 0) scan_.first_seq = env->seq;
    scan_.last_seq = env->seq;
    ++scan_.records;
    if (visitor_.on_record) {
      JournalRecord record{type, env->seq, env->message, pos_};
      CCMD_RETURN_IF_ERROR(visitor_.on_record(record));
    }
    return Status::Ok();
  }

  bool Torn(const std::string& why) {
    scan_.valid_bytes = pos_;
    scan_.torn_bytes = src_->size() - pos_;
    scan_.torn_reason = why;
    return true;
  }

  // Damage at pos_: an error that says what is wrong and what a cut would cost.
  StatusOr<bool> Damaged(const std::string& what) {
    std::string text = name_ + ": " + what + " at offset " + std::to_string(pos_) + " (record " +
                       std::to_string(scan_.records + (scan_.has_info ? 1 : 0)) +
                       ", after sequence number " + std::to_string(scan_.last_seq) + "); ";
    StatusOr<IntactAfter> after = FindIntactAfter(src_, pos_);
    if (!after.ok()) return after.status();
    if (after->records > 0) {
      text += std::to_string(after->records) + " intact record(s) follow it";
      if (after->last_seq != 0) {
        text += " (sequence numbers " + std::to_string(after->first_seq) + ".." +
                std::to_string(after->last_seq) + ")";
      }
      text +=
          ", so this is damage inside the journal, not an interrupted write, and cutting the "
          "file would lose them. Restore the file from a copy, or move it out of the folder "
          "to start without this agent's journal";
    } else {
      text += "nothing after it passes its checks: cutting the file at offset " +
              std::to_string(pos_) + " (truncate -s " + std::to_string(pos_) +
              " FILE) drops only bytes that fail them, and nothing that was acknowledged "
              "unless the disk damaged it";
    }
    return Corrupt(text);
  }

  ScanSource* src_;
  std::string name_;
  const JournalVisitor& visitor_;
  JournalScanOptions options_;
  JournalScan scan_;
  std::uint64_t pos_ = 0;
  std::vector<std::uint8_t> payload_;
};

}  // namespace

std::vector<std::uint8_t> SerializeJournalInfo(const JournalAgentInfo& info) {
  ByteWriter w(128);
  w.PutU16(info.id.value());
  w.PutU8(static_cast<std::uint8_t>(info.name.size()));
  w.PutBytes(info.name.data(), info.name.size());
  PutSessionCamera(info.camera, &w);
  w.PutU32(info.max_payload_bytes);
  w.PutBytes(info.verifier.data(), info.verifier.size());
  // Distortion is appended only when there is some, as in version 1.
  if (info.camera.HasDistortion()) {
    w.PutU8(kJournalCameraDistortion);
    PutSessionDistortion(info.camera, &w);
  }
  if (info.camera.HasDepthNoise()) {
    w.PutU8(kJournalCameraDepthNoise);
    PutSessionDepthNoise(info.camera, &w);
  }
  if (info.camera.HasTrajectoryCamera()) {
    w.PutU8(kJournalCameraTrajectory);
    PutSessionTrajectoryCamera(info.camera, &w);
  }
  return w.Take();
}

namespace {

Status ReadLimitAndVerifier(ByteReader* r, std::uint32_t* limit, IdentityVerifier* verifier) {
  CCMD_RETURN_IF_ERROR(r->ReadU32(limit));
  if (*limit < kFrameHeaderSize || *limit > kMaxJournalPayloadBytes) {
    return Corrupt("journal: payload limit of " + std::to_string(*limit) + " bytes");
  }
  return r->ReadBytes(verifier->size(), verifier->data());
}

}  // namespace

StatusOr<JournalAgentInfo> ParseJournalInfo(ByteSpan payload, std::uint8_t version) {
  ByteReader r(payload);
  JournalAgentInfo info;
  std::uint16_t id;
  CCMD_RETURN_IF_ERROR(r.ReadU16(&id));
  info.id = AgentId(id);
  std::uint8_t n;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&n));
  ByteSpan name;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(n, &name));
  info.name.assign(name.begin(), name.end());
  Status name_ok = ValidateAgentName(info.name);
  if (!name_ok.ok()) return Corrupt("journal info: " + name_ok.message());
  CCMD_RETURN_IF_ERROR(ReadSessionCamera(&r, &info.camera));
  if (version < 2) {
    info.max_payload_bytes = 0;  // version 1 recorded neither limit nor verifier
  } else {
    CCMD_RETURN_IF_ERROR(ReadLimitAndVerifier(&r, &info.max_payload_bytes, &info.verifier));
  }
  std::uint8_t last_extension = 0;
  while (r.remaining() > 0) {
    std::uint8_t extension;
    CCMD_RETURN_IF_ERROR(r.ReadU8(&extension));
    if (extension <= last_extension) {
      return Corrupt("journal info: camera extension " + std::to_string(extension) +
                     " out of order");
    }
    last_extension = extension;
    if (extension == kJournalCameraDistortion) {
      CCMD_RETURN_IF_ERROR(ReadSessionDistortion(&r, &info.camera));
    } else if (extension == kJournalCameraDepthNoise) {
      CCMD_RETURN_IF_ERROR(ReadSessionDepthNoise(&r, &info.camera));
      if (!info.camera.HasDepthNoise()) return Corrupt("journal info: zero depth noise");
    } else if (extension == kJournalCameraTrajectory) {
      CCMD_RETURN_IF_ERROR(ReadSessionTrajectoryCamera(&r, &info.camera));
      if (!info.camera.HasTrajectoryCamera()) {
        return Corrupt("journal info: trajectory camera is the colour camera's");
      }
    } else {
      return Corrupt("journal info: unknown camera extension " + std::to_string(extension) +
                     " (written by a newer server?)");
    }
  }
  CCMD_RETURN_IF_ERROR(r.ExpectEnd());
  Status camera_ok = ValidateSessionCamera(info.camera);
  if (!camera_ok.ok()) return Corrupt("journal info: " + camera_ok.message());
  return info;
}

std::vector<std::uint8_t> SerializeJournalUpdate(const JournalUpdate& update) {
  ByteWriter w(36);
  w.PutU32(update.max_payload_bytes);
  w.PutBytes(update.verifier.data(), update.verifier.size());
  return w.Take();
}

StatusOr<JournalUpdate> ParseJournalUpdate(ByteSpan payload) {
  ByteReader r(payload);
  JournalUpdate update;
  CCMD_RETURN_IF_ERROR(ReadLimitAndVerifier(&r, &update.max_payload_bytes, &update.verifier));
  CCMD_RETURN_IF_ERROR(r.ExpectEnd());
  return update;
}

std::string JournalFileName(AgentId id) {
  char name[32];
  std::snprintf(name, sizeof(name), "agent_%05u.journal", static_cast<unsigned>(id.value()));
  return name;
}

bool ParseJournalFileName(const std::string& name, AgentId* id) {
  static constexpr std::string_view kPrefix = "agent_";
  static constexpr std::string_view kSuffix = ".journal";
  if (name.size() != kPrefix.size() + 5 + kSuffix.size()) return false;
  if (name.compare(0, kPrefix.size(), kPrefix) != 0) return false;
  if (name.compare(name.size() - kSuffix.size(), kSuffix.size(), kSuffix) != 0) return false;
  unsigned value = 0;
  for (std::size_t i = kPrefix.size(); i < kPrefix.size() + 5; ++i) {
    if (name[i] < '0' || name[i] > '9') return false;
    value = value * 10 + static_cast<unsigned>(name[i] - '0');
  }
  if (value > 0xFFFF) return false;
  *id = AgentId(static_cast<std::uint16_t>(value));
  return true;
}

Status SyncDirectory(const std::string& dir) {
  UniqueFd fd(::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (!fd.valid()) return IoError(Errno("opening folder " + dir));
  if (::fsync(fd.get()) != 0) return IoError(Errno("syncing folder " + dir));
  return Status::Ok();
}

StatusOr<std::unique_ptr<JournalWriter>> JournalWriter::Create(const std::string& path,
                                                               const JournalAgentInfo& info) {
  UniqueFd fd(::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_APPEND | O_CLOEXEC, 0644));
  if (!fd.valid()) {
    if (errno == EEXIST) return InvalidArgument("journal " + path + " exists already");
    return IoError(Errno("creating journal " + path));
  }
  const std::vector<std::uint8_t> record =
      EncodeFrame(kJournalInfoRecord, 0, SerializeJournalInfo(info));
  CCMD_RETURN_IF_ERROR(WriteAll(fd.get(), record.data(), record.size(), path));
  if (::fdatasync(fd.get()) != 0) return IoError(Errno("syncing journal " + path));
  const std::size_t slash = path.rfind('/');
  CCMD_RETURN_IF_ERROR(SyncDirectory(slash == std::string::npos ? "." : path.substr(0, slash)));
  return std::unique_ptr<JournalWriter>(new JournalWriter(path, std::move(fd), record.size()));
}

StatusOr<std::unique_ptr<JournalWriter>> JournalWriter::OpenForAppend(const std::string& path,
                                                                      std::uint64_t valid_bytes) {
  UniqueFd fd(::open(path.c_str(), O_WRONLY | O_APPEND | O_CLOEXEC));
  if (!fd.valid()) return IoError(Errno("opening journal " + path));
  struct stat st {};
  if (::fstat(fd.get(), &st) != 0) return IoError(Errno("stat " + path));
  if (static_cast<std::uint64_t>(st.st_size) != valid_bytes) {
    if (::ftruncate(fd.get(), static_cast<off_t>(valid_bytes)) != 0 || ::fsync(fd.get()) != 0) {
      return IoError(Errno("cutting the torn tail of " + path));
    }
  }
  return std::unique_ptr<JournalWriter>(new JournalWriter(path, std::move(fd), valid_bytes));
}

Status JournalWriter::Append(std::uint8_t type, std::uint64_t seq, ByteSpan message) {
  buffer_.clear();
  AppendDataFrame(type, seq, message, &buffer_);
  CCMD_RETURN_IF_ERROR(WriteAll(fd_.get(), buffer_.data(), buffer_.size(), path_));
  size_ += buffer_.size();
  return Status::Ok();
}

Status JournalWriter::AppendUpdate(const JournalUpdate& update) {
  const std::vector<std::uint8_t> record =
      EncodeFrame(kJournalUpdateRecord, 0, SerializeJournalUpdate(update));
  CCMD_RETURN_IF_ERROR(WriteAll(fd_.get(), record.data(), record.size(), path_));
  size_ += record.size();
  return Sync();
}

Status JournalWriter::Sync() {
  if (size_ == synced_size_) return Status::Ok();
  if (::fdatasync(fd_.get()) != 0) return IoError(Errno("syncing journal " + path_));
  synced_size_ = size_;
  return Status::Ok();
}

Status JournalWriter::RollBack() {
  if (::ftruncate(fd_.get(), static_cast<off_t>(synced_size_)) != 0) {
    return IoError(Errno("cutting back journal " + path_));
  }
  size_ = synced_size_;
  return Status::Ok();
}

StatusOr<JournalScan> ScanJournalFile(const std::string& path, const JournalVisitor& visitor,
                                      const JournalScanOptions& options) {
  UniqueFd fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
  if (!fd.valid()) return IoError(Errno("opening journal " + path));
  struct stat st {};
  if (::fstat(fd.get(), &st) != 0) return IoError(Errno("stat " + path));
  FileSource src(fd.get(), static_cast<std::uint64_t>(st.st_size), path);
  return Scanner(&src, path, visitor, options).Run();
}

StatusOr<JournalScan> ScanJournalBytes(ByteSpan bytes, const JournalVisitor& visitor,
                                       const JournalScanOptions& options) {
  MemorySource src(bytes);
  return Scanner(&src, "journal", visitor, options).Run();
}

Status JournalScanOptions::Validate() const {
  if (max_payload_bytes == 0) return InvalidArgument("max_payload_bytes must be positive");
  return Status::Ok();
}

void JournalScanOptions::Describe(OptionsWriter* out) const {
  out->Add("max_payload_bytes", max_payload_bytes);
}

}  // namespace ccmd
