// Test helper: serves the BehaviorSystem service (no overrides, so every
// method is UNIMPLEMENTED), the default health service and our reflection
// services, then prints "port=<N>" on stdout and runs until SIGTERM/SIGINT.
//
//   reflection_demo_server [address]   (default 127.0.0.1:0)

#include <grpcpp/grpcpp.h>
#include <signal.h>

#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "behaviorlib/reflection/reflection_service.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"

int main(int argc, char** argv) {
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  const std::string address = argc > 1 ? argv[1] : "127.0.0.1:0";
  grpc::EnableDefaultHealthCheckService(true);
  behaviorlib::v1::BehaviorSystem::Service behavior_system;
  auto reflection = behaviorlib::makeReflectionServices(
      {"behaviorlib.v1.BehaviorSystem", "grpc.health.v1.Health"});
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort(address, grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&behavior_system);
  for (auto& service : reflection) builder.RegisterService(service.get());
  auto server = builder.BuildAndStart();
  if (!server || port == 0) {
    std::fprintf(stderr, "reflection_demo_server: cannot listen on %s\n", address.c_str());
    return 1;
  }
  std::printf("port=%d\n", port);
  std::fflush(stdout);

  int sig = 0;
  sigwait(&signals, &sig);
  server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(1));
  return 0;
}
