// The authorizer (makeAuthorizer) on a real TLS server in this process:
// gRPC hands the AuthMetadataProcessor the connection's AuthContext, so
// anything it added per call would pile up for the connection's life (it
// once did: 500 µs per call after 10,000 calls, and memory without bound).
// Many calls on one connection must leave the context as it was, and the
// handler must still see who called (callerOf).

#include <grpcpp/generic/async_generic_service.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <condition_variable>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <sstream>
#include <string>
#include <vector>

#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::server {
namespace {

std::string read(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// Answers every method OK, noting the caller and the size of the call's
// auth context.
class Recorder final : public grpc::CallbackGenericService {
 public:
  grpc::ServerGenericBidiReactor* CreateReactor(
      grpc::GenericCallbackServerContext* context) override {
    {
      std::lock_guard lock(mutex_);
      size_t properties = 0;
      for (auto it = context->auth_context()->begin(); it != context->auth_context()->end(); ++it) {
        ++properties;
      }
      property_counts.push_back(properties);
      const auto caller = callerOf(*context);
      callers.push_back(caller ? caller->identity : "");
    }
    class Reactor final : public grpc::ServerGenericBidiReactor {
     public:
      Reactor() { Finish(grpc::Status::OK); }
      void OnDone() override { delete this; }
    };
    return new Reactor();
  }
  std::mutex mutex_;
  std::vector<size_t> property_counts;
  std::vector<std::string> callers;
};

TEST(AuthorizerInProcessTest, ManyCallsOnOneConnectionLeaveItsAuthContextAlone) {
  char dir[] = "/tmp/authorizer_test_XXXXXX";
  ASSERT_NE(mkdtemp(dir), nullptr);
  const std::string certs = std::string(dir) + "/certs";
  ASSERT_EQ(std::system((std::string(BEHAVIORLIB_MAKE_DEV_CERTS) + " --out " + certs +
                         " server operator > /dev/null")
                            .c_str()),
            0);
  auto policy = AccessPolicy::parse(
      "identities:\n  - certificate: behaviorlib:operator\n    roles: [viewer, operator]\n",
      "policy.yaml");
  ASSERT_TRUE(policy.ok()) << policy.status();
  auto shared = std::make_shared<const AccessPolicy>(std::move(*policy));
  setProcessAccessPolicy(shared);

  grpc::SslServerCredentialsOptions options(
      GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  options.pem_root_certs = read(certs + "/ca.pem");
  options.pem_key_cert_pairs.push_back({read(certs + "/server.key"), read(certs + "/server.pem")});
  auto credentials = grpc::SslServerCredentials(options);
  credentials->SetAuthMetadataProcessor(makeAuthorizer(shared, nullptr));
  Recorder recorder;
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", credentials, &port);
  builder.RegisterCallbackGenericService(&recorder);
  auto server = builder.BuildAndStart();
  ASSERT_NE(server, nullptr);

  grpc::SslCredentialsOptions client;
  client.pem_root_certs = read(certs + "/ca.pem");
  client.pem_private_key = read(certs + "/operator.key");
  client.pem_cert_chain = read(certs + "/operator.pem");
  auto channel =
      grpc::CreateChannel("127.0.0.1:" + std::to_string(port), grpc::SslCredentials(client));
  grpc::GenericStub stub(channel);
  for (int i = 0; i < 200; ++i) {
    grpc::ClientContext context;
    grpc::Slice empty("", 0);
    grpc::ByteBuffer request(&empty, 1), response;
    std::mutex mutex;
    std::condition_variable done_cv;
    bool done = false;
    grpc::Status status;
    stub.UnaryCall(&context, "/behaviorlib.v1.Coordinator/WriteBelief", grpc::StubOptions(),
                   &request, &response, orderedCallback([&](grpc::Status s) {
                     std::lock_guard lock(mutex);
                     status = s;
                     done = true;
                     done_cv.notify_all();
                   }));
    std::unique_lock lock(mutex);
    done_cv.wait(lock, [&] { return done; });
    ASSERT_TRUE(status.ok()) << i << ": " << status.error_message();
  }
  server->Shutdown();
  setProcessAccessPolicy(nullptr);
  std::filesystem::remove_all(dir);

  std::lock_guard lock(recorder.mutex_);
  ASSERT_EQ(recorder.property_counts.size(), 200u);
  EXPECT_EQ(recorder.property_counts.front(), recorder.property_counts.back())
      << "the connection's auth context grew from " << recorder.property_counts.front() << " to "
      << recorder.property_counts.back() << " properties";
  EXPECT_EQ(recorder.callers.front(), "behaviorlib:operator");
  EXPECT_EQ(recorder.callers.back(), "behaviorlib:operator");
}

}  // namespace
}  // namespace behaviorlib::server
