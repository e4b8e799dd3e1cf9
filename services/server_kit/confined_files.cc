#include "behaviorlib/server_kit/confined_files.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <cstdlib>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/error_details.h"

namespace behaviorlib::server_kit {
namespace {

// realpath(3), or empty when the path does not resolve.
std::string realPath(const std::string& path) {
  char buffer[PATH_MAX];
  if (::realpath(path.c_str(), buffer) == nullptr) return {};
  return buffer;
}

class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) ::close(fd_);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  int get() const { return fd_; }

 private:
  int fd_;
};

// A file that does not exist or cannot be read.
absl::Status fileNotFound(absl::Status status, const std::string& path) {
  return errors::withReason(std::move(status), v1::FILE_NOT_FOUND, {{"path", path}});
}

absl::Status fileTooLarge(absl::Status status, const std::string& path, size_t max_bytes) {
  return errors::withReason(std::move(status), v1::FILE_TOO_LARGE,
                            {{"path", path}, {"limit", std::to_string(max_bytes)}});
}

// Reads an open descriptor of a regular file, at most max_bytes.
absl::StatusOr<std::string> readCapped(int fd, const std::string& path, size_t max_bytes) {
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    return fileNotFound(
        absl::InternalError(absl::StrCat(path, ": cannot stat: ", std::strerror(errno))), path);
  }
  if (!S_ISREG(st.st_mode)) {
    return fileNotFound(absl::InvalidArgumentError(absl::StrCat(path, ": not a regular file")),
                        path);
  }
  if (static_cast<size_t>(st.st_size) > max_bytes) {
    return fileTooLarge(
        absl::ResourceExhaustedError(
            absl::StrCat(path, ": ", st.st_size, " bytes, more than the ", max_bytes, " allowed")),
        path, max_bytes);
  }
  std::string out;
  char chunk[65536];
  for (;;) {
    const ssize_t n = ::read(fd, chunk, sizeof chunk);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      return fileNotFound(
          absl::InternalError(absl::StrCat(path, ": cannot read: ", std::strerror(errno))), path);
    }
    if (n == 0) break;
    out.append(chunk, static_cast<size_t>(n));
    // The file grew after the stat.
    if (out.size() > max_bytes) {
      return fileTooLarge(absl::ResourceExhaustedError(
                              absl::StrCat(path, ": more than the ", max_bytes, " bytes allowed")),
                          path, max_bytes);
    }
  }
  return out;
}

}  // namespace

absl::StatusOr<ConfinedDirectory> ConfinedDirectory::open(std::string purpose,
                                                          const std::string& root,
                                                          size_t max_read_bytes) {
  if (root.empty()) return ConfinedDirectory(std::move(purpose), "", max_read_bytes);
  const std::string resolved = realPath(root);
  struct stat st {};
  if (resolved.empty() || ::stat(resolved.c_str(), &st) != 0 || !S_ISDIR(st.st_mode)) {
    return absl::InvalidArgumentError(
        absl::StrCat("the directory for ", purpose, " '", root, "' does not exist"));
  }
  return ConfinedDirectory(std::move(purpose), resolved, max_read_bytes);
}

absl::Status ConfinedDirectory::refuse(const std::string& requested, const std::string& why) const {
  if (root_.empty()) {
    // No directory is allowed: every path is outside.
    return errors::withReason(
        absl::PermissionDeniedError(
            absl::StrCat("'", requested, "' refused: no directory is configured for ", purpose_)),
        v1::PATH_OUTSIDE_ALLOWED_DIRECTORY, {{"path", requested}});
  }
  return errors::withReason(absl::PermissionDeniedError(absl::StrCat(
                                purpose_, " must be inside ", root_, ": '", requested, "' ", why)),
                            v1::PATH_OUTSIDE_ALLOWED_DIRECTORY,
                            {{"path", requested}, {"allowed_directory", root_}});
}

absl::StatusOr<std::string> ConfinedDirectory::lexical(const std::string& requested) const {
  if (root_.empty()) return refuse(requested, "");
  if (requested.empty()) {
    return errors::withReason(absl::InvalidArgumentError("the path is empty"), v1::INVALID_REQUEST);
  }
  if (requested.find('\0') != std::string::npos) {
    return errors::withReason(absl::InvalidArgumentError("the path contains a NUL character"),
                              v1::INVALID_REQUEST);
  }
  if (requested.size() > PATH_MAX) {
    return errors::withReason(
        absl::InvalidArgumentError(absl::StrCat("the path is longer than ", PATH_MAX, " bytes")),
        v1::INVALID_REQUEST, {{"limit", std::to_string(PATH_MAX)}});
  }
  for (absl::string_view part : absl::StrSplit(requested, '/')) {
    if (part == "..") return refuse(requested, "has a '..' component");
  }
  return requested.front() == '/' ? requested : root_ + "/" + requested;
}

bool ConfinedDirectory::inside(const std::string& resolved) const {
  return resolved == root_ ||
         (resolved.size() > root_.size() && resolved.compare(0, root_.size(), root_) == 0 &&
          (root_ == "/" || resolved[root_.size()] == '/'));
}

absl::StatusOr<std::string> ConfinedDirectory::resolveExisting(const std::string& requested) const {
  absl::StatusOr<std::string> full = lexical(requested);
  if (!full.ok()) return full.status();
  const std::string resolved = realPath(*full);
  if (resolved.empty()) {
    if (!inside(*full)) return refuse(requested, "is outside it");
    return fileNotFound(absl::NotFoundError(absl::StrCat(purpose_, ": '", requested,
                                                         "' does not exist in ", root_)),
                        requested);
  }
  if (!inside(resolved)) return refuse(requested, "resolves outside it");
  return resolved;
}

absl::StatusOr<std::string> ConfinedDirectory::resolveForWrite(const std::string& requested) const {
  absl::StatusOr<std::string> full = lexical(requested);
  if (!full.ok()) return full.status();
  const size_t slash = full->find_last_of('/');
  const std::string name = full->substr(slash + 1);
  if (name.empty() || name == ".") return refuse(requested, "names no file");
  const std::string parent = realPath(slash == 0 ? "/" : full->substr(0, slash));
  if (parent.empty()) {
    return fileNotFound(absl::NotFoundError(absl::StrCat(purpose_, ": the directory of '",
                                                         requested, "' does not exist")),
                        requested);
  }
  const std::string target = (parent == "/" ? "" : parent) + "/" + name;
  if (!inside(parent) || target == root_) return refuse(requested, "is outside it");
  struct stat st {};
  if (::lstat(target.c_str(), &st) == 0 && !S_ISREG(st.st_mode)) {
    return refuse(requested, "exists and is not a regular file (a link, a device or a directory)");
  }
  return target;
}

absl::StatusOr<std::string> ConfinedDirectory::write(const std::string& requested,
                                                     std::string_view contents) const {
  absl::StatusOr<std::string> target = resolveForWrite(requested);
  if (!target.ok()) return target.status();
  const size_t slash = target->find_last_of('/');
  const std::string parent = slash == 0 ? "/" : target->substr(0, slash);
  const std::string name = target->substr(slash + 1);
  Fd dir(::open(parent.c_str(), O_RDONLY | O_DIRECTORY | O_NOFOLLOW | O_CLOEXEC));
  if (dir.get() < 0) {
    return absl::PermissionDeniedError(absl::StrCat(purpose_, ": cannot open the directory of '",
                                                    requested, "': ", std::strerror(errno)));
  }
  // A fresh name: O_EXCL never opens what is there, link or file.
  std::string temporary;
  int fd = -1;
  for (int attempt = 0; attempt < 100 && fd < 0; ++attempt) {
    temporary = absl::StrCat(".", name, ".", ::getpid(), ".", attempt, ".tmp");
    fd = ::openat(dir.get(), temporary.c_str(),
                  O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0644);
    if (fd < 0 && errno != EEXIST) break;
  }
  if (fd < 0) {
    return absl::PermissionDeniedError(
        absl::StrCat(purpose_, ": cannot write '", requested, "': ", std::strerror(errno)));
  }
  Fd file(fd);
  const auto fail = [&](const char* what) {
    const std::string why = std::strerror(errno);
    ::unlinkat(dir.get(), temporary.c_str(), 0);
    return absl::InternalError(
        absl::StrCat(purpose_, ": cannot ", what, " '", requested, "': ", why));
  };
  for (size_t done = 0; done < contents.size();) {
    const ssize_t n = ::write(file.get(), contents.data() + done, contents.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) return fail("write");
    done += static_cast<size_t>(n);
  }
  if (::fsync(file.get()) != 0) return fail("write");
  if (::renameat(dir.get(), temporary.c_str(), dir.get(), name.c_str()) != 0) {
    return fail("replace");
  }
  return target;
}

absl::StatusOr<std::string> ConfinedDirectory::read(const std::string& requested) const {
  absl::StatusOr<std::string> path = resolveExisting(requested);
  if (!path.ok()) return path.status();
  // O_NOFOLLOW: the resolved path has no link left; one appearing since is refused.
  Fd fd(::open(path->c_str(), O_RDONLY | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC));
  if (fd.get() < 0) {
    return fileNotFound(absl::PermissionDeniedError(absl::StrCat(
                            purpose_, ": cannot open '", requested, "': ", std::strerror(errno))),
                        requested);
  }
  return readCapped(fd.get(), requested, max_read_bytes_);
}

absl::StatusOr<std::string> readFileCapped(const std::string& path, size_t max_bytes) {
  Fd fd(::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC));
  if (fd.get() < 0) {
    return fileNotFound(
        absl::NotFoundError(absl::StrCat(path, ": cannot open: ", std::strerror(errno))), path);
  }
  return readCapped(fd.get(), path, max_bytes);
}

}  // namespace behaviorlib::server_kit
