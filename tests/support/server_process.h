#pragma once

// Starts a real server binary for an integration test, listening on a free
// loopback port chosen by the kernel (`--listen 127.0.0.1:0`), and reads the
// bound ports from the file the server writes with `--port-file`.
//
//   support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
//   ASSERT_TRUE(broker.start()) << broker.error();
//   auto stub = DataChannel::NewStub(grpc::CreateChannel(broker.address(), ...));
//   int code = broker.terminate();   // SIGTERM, waits, returns the exit code

#include <sys/types.h>

#include <chrono>
#include <string>
#include <vector>

namespace support {

class ServerProcess {
 public:
  /// `args` are appended after `--listen 127.0.0.1:0 --metrics-listen
  /// 127.0.0.1:0 --port-file <tmp>`.
  ServerProcess(std::string binary, std::vector<std::string> args);
  /// `leading` come right after `binary`, before the flags: a script after
  /// its interpreter (`python3 system.py --listen ...`).
  ServerProcess(std::string binary, std::vector<std::string> leading,
                std::vector<std::string> args);
  ~ServerProcess();  // kills the process if still running
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  /// Starts the process and waits (up to `timeout`) until the port file
  /// appears. False with error() set on failure.
  bool start(std::chrono::milliseconds timeout = std::chrono::seconds(10));
  /// "127.0.0.1:<grpc port>".
  std::string address() const;
  int grpcPort() const { return grpc_port_; }
  int metricsPort() const { return metrics_port_; }
  pid_t pid() const { return pid_; }
  bool running() const { return pid_ > 0; }
  const std::string& error() const { return error_; }

  /// Sends SIGTERM and waits up to `timeout`; returns the exit code, or
  /// 128+signal, or -1 if it had to be killed.
  int terminate(std::chrono::milliseconds timeout = std::chrono::seconds(10));
  /// Sends SIGKILL and reaps (simulates a crash).
  void kill();
  /// Waits for the process to exit by itself (up to `timeout`); exit code or -1.
  int wait(std::chrono::milliseconds timeout);
  /// Sends SIGSTOP and waits (up to `timeout`) until every one of its threads
  /// is stopped. kill(2) returns before that: the stop reaches the other
  /// threads only once the thread that took the signal runs, and on a busy
  /// machine another thread can answer a request in between. False with
  /// error() set when a thread was still running at the timeout.
  bool freeze(std::chrono::milliseconds timeout = std::chrono::seconds(10));
  /// Sends SIGCONT.
  bool thaw();

 private:
  std::string binary_;
  std::vector<std::string> leading_;
  std::vector<std::string> args_;
  std::string port_file_;
  std::string error_;
  pid_t pid_ = -1;
  int grpc_port_ = 0;
  int metrics_port_ = 0;
};

/// Reads "key=value" lines of a port file; 0 when the key is absent.
int readPortFromFile(const std::string& path, const std::string& key);

/// HTTP GET http://127.0.0.1:<port><path> (blocking, for /metrics); the body,
/// or "" on failure.
std::string httpGet(int port, const std::string& path);

}  // namespace support
