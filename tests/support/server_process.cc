#include "support/server_process.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

namespace support {
namespace {

std::string tempPath() {
  char tmpl[] = "/tmp/behaviorlib-ports-XXXXXX";
  int fd = mkstemp(tmpl);
  if (fd >= 0) close(fd);
  unlink(tmpl);  // the server creates it when its ports are bound
  return tmpl;
}

int reap(pid_t pid, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (true) {
    int status = 0;
    pid_t r = waitpid(pid, &status, WNOHANG);
    if (r == pid) {
      if (WIFEXITED(status)) return WEXITSTATUS(status);
      if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
      return -1;
    }
    if (r < 0) return -1;
    if (std::chrono::steady_clock::now() > deadline) return -2;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
}

// The state letter of /proc/<pid>/task/<tid>/stat: after the command's
// closing parenthesis (the command may itself hold spaces and parentheses).
char threadState(const std::filesystem::path& stat_path) {
  std::ifstream in(stat_path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto close = text.rfind(')');
  if (close == std::string::npos || close + 2 >= text.size()) return '?';
  return text[close + 2];
}

// Every thread of `pid` is stopped by a signal ('T'); a thread that exited
// meanwhile is skipped.
bool allThreadsStopped(pid_t pid, std::string* running) {
  std::error_code ec;
  const std::filesystem::path tasks = "/proc/" + std::to_string(pid) + "/task";
  for (const auto& entry : std::filesystem::directory_iterator(tasks, ec)) {
    const char state = threadState(entry.path() / "stat");
    if (state == '?') continue;
    if (state != 'T') {
      *running = entry.path().filename().string() + " in state " + std::string(1, state);
      return false;
    }
  }
  return !ec;
}

}  // namespace

int readPortFromFile(const std::string& path, const std::string& key) {
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    auto eq = line.find('=');
    if (eq != std::string::npos && line.substr(0, eq) == key) {
      return std::atoi(line.c_str() + eq + 1);
    }
  }
  return 0;
}

ServerProcess::ServerProcess(std::string binary, std::vector<std::string> args)
    : binary_(std::move(binary)), args_(std::move(args)), port_file_(tempPath()) {}

ServerProcess::ServerProcess(std::string binary, std::vector<std::string> leading,
                             std::vector<std::string> args)
    : binary_(std::move(binary)),
      leading_(std::move(leading)),
      args_(std::move(args)),
      port_file_(tempPath()) {}

ServerProcess::~ServerProcess() {
  if (pid_ > 0) kill();
  unlink(port_file_.c_str());
}

bool ServerProcess::start(std::chrono::milliseconds timeout) {
  std::vector<std::string> argv_s = {binary_};
  argv_s.insert(argv_s.end(), leading_.begin(), leading_.end());
  for (const char* flag :
       {"--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0", "--port-file"}) {
    argv_s.emplace_back(flag);
  }
  argv_s.push_back(port_file_);
  argv_s.insert(argv_s.end(), args_.begin(), args_.end());
  std::vector<char*> argv;
  for (auto& a : argv_s) argv.push_back(a.data());
  argv.push_back(nullptr);
  pid_ = fork();
  if (pid_ < 0) {
    error_ = "fork failed";
    return false;
  }
  if (pid_ == 0) {
    execv(argv[0], argv.data());
    std::perror("execv");
    _exit(127);
  }
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    grpc_port_ = readPortFromFile(port_file_, "grpc_port");
    if (grpc_port_ > 0) {
      metrics_port_ = readPortFromFile(port_file_, "metrics_port");
      return true;
    }
    int status = 0;
    if (waitpid(pid_, &status, WNOHANG) == pid_) {
      error_ = binary_ + " exited before binding its port";
      pid_ = -1;
      return false;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  error_ = binary_ + " did not write its port file in time";
  kill();
  return false;
}

std::string ServerProcess::address() const { return "127.0.0.1:" + std::to_string(grpc_port_); }

int ServerProcess::terminate(std::chrono::milliseconds timeout) {
  if (pid_ <= 0) return -1;
  ::kill(pid_, SIGTERM);
  int code = reap(pid_, timeout);
  if (code == -2) {
    kill();
    return -1;
  }
  pid_ = -1;
  return code;
}

void ServerProcess::kill() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGKILL);
  reap(pid_, std::chrono::seconds(5));
  pid_ = -1;
}

int ServerProcess::wait(std::chrono::milliseconds timeout) {
  if (pid_ <= 0) return -1;
  int code = reap(pid_, timeout);
  if (code == -2) return -1;
  pid_ = -1;
  return code;
}

bool ServerProcess::freeze(std::chrono::milliseconds timeout) {
  if (pid_ <= 0 || ::kill(pid_, SIGSTOP) != 0) {
    error_ = "cannot send SIGSTOP";
    return false;
  }
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  std::string running;
  while (!allThreadsStopped(pid_, &running)) {
    if (std::chrono::steady_clock::now() > deadline) {
      error_ = "SIGSTOP sent, but thread " + running + " after the timeout";
      return false;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  return true;
}

bool ServerProcess::thaw() { return pid_ > 0 && ::kill(pid_, SIGCONT) == 0; }

std::string httpGet(int port, const std::string& path) {
  int fd = socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return "";
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
    close(fd);
    return "";
  }
  std::string req = "GET " + path + " HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n";
  if (write(fd, req.data(), req.size()) < 0) {
    close(fd);
    return "";
  }
  std::string out;
  char buf[4096];
  ssize_t n;
  while ((n = read(fd, buf, sizeof(buf))) > 0) out.append(buf, static_cast<size_t>(n));
  close(fd);
  auto body = out.find("\r\n\r\n");
  return body == std::string::npos ? "" : out.substr(body + 4);
}

}  // namespace support
