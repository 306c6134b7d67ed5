#include "libccmd/net/spill_store.h"

#include <dirent.h>
#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>

#include "libccmd/net/session_messages.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "proto/frame.h"

namespace ccmd {
namespace {

constexpr const char* kSegmentSuffix = ".spill";

std::string Errno(const std::string& what) { return what + ": " + std::strerror(errno); }

bool IsSegmentName(const std::string& name) {
  const std::string suffix = kSegmentSuffix;
  return name.size() > suffix.size() &&
         name.compare(name.size() - suffix.size(), suffix.size(), suffix) == 0 &&
         name.compare(0, 8, "segment_") == 0;
}

}  // namespace

StatusOr<std::unique_ptr<SpillStore>> SpillStore::Open(const std::string& dir,
                                                       std::uint64_t max_bytes,
                                                       std::uint64_t segment_bytes) {
  if (dir.empty()) return InvalidArgument("spill folder not set");
  if (segment_bytes == 0) return InvalidArgument("spill segment size must be positive");
  CCMD_RETURN_IF_ERROR(MakeDirectories(dir));
  const std::string lock_path = JoinPath(dir, "LOCK");
  UniqueFd lock(::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644));
  if (!lock.valid()) return IoError(Errno("opening " + lock_path));
  if (::flock(lock.get(), LOCK_EX | LOCK_NB) != 0) {
    return Unavailable("spill folder " + dir + " is in use by another agent link");
  }
  // Segments left by an earlier process belonged to a link that no longer exists.
  if (DIR* d = ::opendir(dir.c_str())) {
    int removed = 0;
    while (dirent* e = ::readdir(d)) {
      const std::string name = e->d_name;
      if (IsSegmentName(name) && ::unlink(JoinPath(dir, name).c_str()) == 0) ++removed;
    }
    ::closedir(d);
    if (removed > 0) {
      CCMD_LOG(WARNING) << "spill folder " << dir << ": removed " << removed
                        << " segment(s) left by an earlier run";
    }
  }
  return std::unique_ptr<SpillStore>(
      new SpillStore(dir, std::move(lock), max_bytes, segment_bytes));
}

SpillStore::~SpillStore() {
  while (!segments_.empty()) DropSegment();
}

Status SpillStore::StartSegment() {
  Segment s;
  s.number = next_segment_++;
  char name[48];
  std::snprintf(name, sizeof(name), "segment_%08llu%s", static_cast<unsigned long long>(s.number),
                kSegmentSuffix);
  s.path = JoinPath(dir_, name);
  s.fd = UniqueFd(::open(s.path.c_str(), O_RDWR | O_CREAT | O_TRUNC | O_APPEND | O_CLOEXEC, 0644));
  if (!s.fd.valid()) return IoError(Errno("creating spill segment " + s.path));
  segments_.push_back(std::move(s));
  return Status::Ok();
}

void SpillStore::DropSegment() {
  Segment& s = segments_.front();
  disk_bytes_ -= s.size;
  ::unlink(s.path.c_str());
  segments_.pop_front();
}

Status SpillStore::Push(std::uint8_t type, std::uint64_t seq, ByteSpan message) {
  const std::uint64_t frame_bytes = kFrameHeaderSize + kDataEnvelopeBytes + message.size();
  if (disk_bytes_ + frame_bytes > max_bytes_) {
    return OutOfRange("spill folder " + dir_ + " is full (" + std::to_string(disk_bytes_) + " of " +
                      std::to_string(max_bytes_) + " bytes)");
  }
  if (segments_.empty() || segments_.back().size >= segment_bytes_) {
    CCMD_RETURN_IF_ERROR(StartSegment());
  }
  Segment& s = segments_.back();
  buffer_.clear();
  AppendDataFrame(type, seq, message, &buffer_);
  std::size_t done = 0;
  while (done < buffer_.size()) {
    const ssize_t n = ::write(s.fd.get(), buffer_.data() + done, buffer_.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const Status error = IoError(Errno("writing spill segment " + s.path));
      // Keep the segment consistent with the index: cut the partial record.
      if (::ftruncate(s.fd.get(), static_cast<off_t>(s.size)) != 0) {
        CCMD_LOG(WARNING) << "cannot cut " << s.path << ": " << std::strerror(errno);
      }
      return error;
    }
    done += static_cast<std::size_t>(n);
  }
  index_.push_back(Entry{s.number, s.size, buffer_.size(), message.size()});
  s.size += buffer_.size();
  ++s.unread;
  disk_bytes_ += buffer_.size();
  return Status::Ok();
}

StatusOr<SpilledMessage> SpillStore::Pop() {
  CCMD_CHECK(!index_.empty());
  const Entry e = index_.front();
  index_.pop_front();
  CCMD_CHECK(!segments_.empty() && segments_.front().number == e.segment);
  Segment& s = segments_.front();
  buffer_.resize(e.frame_bytes);
  std::size_t done = 0;
  Status status;
  while (done < buffer_.size()) {
    const ssize_t n = ::pread(s.fd.get(), buffer_.data() + done, buffer_.size() - done,
                              static_cast<off_t>(e.offset + done));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      status = IoError(Errno("reading spill segment " + s.path));
      break;
    }
    done += static_cast<std::size_t>(n);
  }
  --s.unread;
  if (s.unread == 0) DropSegment();
  CCMD_RETURN_IF_ERROR(status);
  CCMD_ASSIGN_OR_RETURN(Frame frame, DecodeFrame(buffer_));
  CCMD_ASSIGN_OR_RETURN(DataEnvelope env, ParseDataEnvelope(frame.payload));
  SpilledMessage m;
  m.type = frame.type;
  m.seq = env.seq;
  m.message.assign(env.message.begin(), env.message.end());
  return m;
}

}  // namespace ccmd
