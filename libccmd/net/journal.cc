#include "libccmd/net/journal.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>

#include "proto/crc32c.h"
#include "proto/frame.h"

namespace ccmd {
namespace {

// Optional trailer of the info record: this byte, then the camera's 5 distortion coefficients.
constexpr std::uint8_t kJournalCameraDistortion = 1;

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

StatusOr<JournalScan> Scan(ScanSource* src, const std::string& name, const JournalVisitor& visitor,
                           const JournalScanOptions& options) {
  JournalScan scan;
  std::uint64_t pos = 0;
  const std::uint64_t size = src->size();
  std::vector<std::uint8_t> payload;
  auto corrupt = [&](const std::string& what) {
    return Corrupt(name + ": " + what + " at offset " + std::to_string(pos) + " (record " +
                   std::to_string(scan.records + (scan.has_info ? 1 : 0)) + ", after sequence " +
                   std::to_string(scan.last_seq) +
                   "); records after it would be lost: move the file aside or cut it at this "
                   "offset to accept that");
  };
  auto torn = [&](const std::string& why) {
    scan.valid_bytes = pos;
    scan.torn_bytes = size - pos;
    scan.torn_reason = why;
    return scan;
  };
  while (pos < size) {
    if (size - pos < kFrameHeaderSize) return torn("incomplete record header");
    std::uint8_t header_bytes[kFrameHeaderSize];
    CCMD_RETURN_IF_ERROR(src->Read(pos, kFrameHeaderSize, header_bytes));
    StatusOr<FrameHeader> header =
        ParseFrameHeader(ByteSpan(header_bytes, kFrameHeaderSize),
                         FrameLimits{.max_payload_bytes = options.max_payload_bytes});
    if (!header.ok()) {
      CCMD_ASSIGN_OR_RETURN(const bool zeros, AllZeroFrom(src, pos));
      if (zeros) return torn("zero-filled tail");
      return corrupt("bad record header (" + header.status().message() + ")");
    }
    const std::uint64_t end = pos + kFrameHeaderSize + header->payload_size;
    if (end > size) return torn("incomplete record");
    payload.resize(header->payload_size);
    if (!payload.empty()) {
      CCMD_RETURN_IF_ERROR(src->Read(pos + kFrameHeaderSize, payload.size(), payload.data()));
    }
    if (Crc32c(payload) != header->payload_crc) {
      // Only the last record can be half-persisted by a crash.
      if (end == size) return torn("last record fails its CRC");
      return corrupt("record payload CRC mismatch");
    }
    if (!scan.has_info) {
      if (header->type != kJournalInfoRecord)
        return corrupt("first record is not a journal info record");
      StatusOr<JournalAgentInfo> info = ParseJournalInfo(payload);
      if (!info.ok()) return corrupt(info.status().message());
      scan.info = std::move(*info);
      scan.has_info = true;
      if (visitor.on_info) CCMD_RETURN_IF_ERROR(visitor.on_info(scan.info));
    } else {
      if (!IsKnownDataType(header->type)) {
        return corrupt("record of unknown type " + std::to_string(header->type));
      }
      StatusOr<DataEnvelope> env = ParseDataEnvelope(payload);
      if (!env.ok()) return corrupt(env.status().message());
      if (env->seq <= scan.last_seq) {
        return corrupt("sequence number " + std::to_string(env->seq) + " does not increase");
      }
      if (scan.last_seq != 0 && env->seq != scan.last_seq + 1) ++scan.gaps;
      if (scan.records == 0) scan.first_seq = env->seq;
      scan.last_seq = env->seq;
      ++scan.records;
      if (visitor.on_record) {
        JournalRecord record{header->type, env->seq, env->message, pos};
        CCMD_RETURN_IF_ERROR(visitor.on_record(record));
      }
    }
    pos = end;
  }
  scan.valid_bytes = pos;
  return scan;
}

}  // namespace

std::vector<std::uint8_t> SerializeJournalInfo(const JournalAgentInfo& info) {
  ByteWriter w(128);
  w.PutU16(info.id.value());
  w.PutU8(static_cast<std::uint8_t>(info.name.size()));
  w.PutBytes(info.name.data(), info.name.size());
  PutSessionCamera(info.camera, &w);
  // Distortion is appended only when there is some: such journals stay readable by servers
  // that predate it, and theirs by this one.
  if (info.camera.HasDistortion()) {
    w.PutU8(kJournalCameraDistortion);
    PutDistortion(info.camera, &w);
  }
  return w.Take();
}

StatusOr<JournalAgentInfo> ParseJournalInfo(ByteSpan payload) {
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
  if (r.remaining() > 0) {
    std::uint8_t extension;
    CCMD_RETURN_IF_ERROR(r.ReadU8(&extension));
    if (extension != kJournalCameraDistortion) {
      return Corrupt("journal info: unknown camera extension " + std::to_string(extension) +
                     " (written by a newer server?)");
    }
    CCMD_RETURN_IF_ERROR(ReadDistortion(&r, &info.camera));
  }
  Status camera_ok = ValidateSessionCamera(info.camera);
  if (!camera_ok.ok()) return Corrupt("journal info: " + camera_ok.message());
  CCMD_RETURN_IF_ERROR(r.ExpectEnd());
  return info;
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
  return Scan(&src, path, visitor, options);
}

StatusOr<JournalScan> ScanJournalBytes(ByteSpan bytes, const JournalVisitor& visitor,
                                       const JournalScanOptions& options) {
  MemorySource src(bytes);
  return Scan(&src, "journal", visitor, options);
}

Status JournalScanOptions::Validate() const {
  if (max_payload_bytes == 0) return InvalidArgument("max_payload_bytes must be positive");
  return Status::Ok();
}

void JournalScanOptions::Describe(OptionsWriter* out) const {
  out->Add("max_payload_bytes", max_payload_bytes);
}

}  // namespace ccmd
