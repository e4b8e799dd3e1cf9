// The authorizer (makeAuthorizer) on a real TLS server in this process:
// gRPC hands the AuthMetadataProcessor the connection's AuthContext, so
// anything it added per call would pile up for the connection's life (it
// once did: 500 µs per call after 10,000 calls, and memory without bound).
// Many calls on one connection must leave the context as it was, and the
// handler must still see who called (callerOf). A refused call's details
// are rebuilt on the client.

#include <grpcpp/generic/async_generic_service.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <condition_variable>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <vector>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::server_kit {
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

// A real TLS server with the authorizer and an operator's client channel.
class AuthorizerInProcessTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_NE(mkdtemp(dir_), nullptr);
    const std::string certs = std::string(dir_) + "/certs";
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
    options.pem_key_cert_pairs.push_back(
        {read(certs + "/server.key"), read(certs + "/server.pem")});
    auto credentials = grpc::SslServerCredentials(options);
    credentials->SetAuthMetadataProcessor(makeAuthorizer(shared, nullptr));
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", credentials, &port);
    builder.RegisterCallbackGenericService(&recorder_);
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);

    grpc::SslCredentialsOptions client;
    client.pem_root_certs = read(certs + "/ca.pem");
    client.pem_private_key = read(certs + "/operator.key");
    client.pem_cert_chain = read(certs + "/operator.pem");
    stub_ = std::make_unique<grpc::GenericStub>(
        grpc::CreateChannel("127.0.0.1:" + std::to_string(port), grpc::SslCredentials(client)));
  }

  void TearDown() override {
    if (server_) server_->Shutdown();
    setProcessAccessPolicy(nullptr);
    std::filesystem::remove_all(dir_);
  }

  // One unary call of `method` with an empty request, as the operator.
  grpc::Status call(const std::string& method) {
    grpc::ClientContext context;
    grpc::Slice empty("", 0);
    grpc::ByteBuffer request(&empty, 1), response;
    std::mutex mutex;
    std::condition_variable done_cv;
    bool done = false;
    grpc::Status status;
    stub_->UnaryCall(&context, method, grpc::StubOptions(), &request, &response,
                     orderedCallback([&](grpc::Status s) {
                       std::lock_guard lock(mutex);
                       status = s;
                       done = true;
                       done_cv.notify_all();
                     }));
    std::unique_lock lock(mutex);
    done_cv.wait(lock, [&] { return done; });
    return status;
  }

  char dir_[64] = "/tmp/authorizer_test_XXXXXX";
  Recorder recorder_;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<grpc::GenericStub> stub_;
};

TEST_F(AuthorizerInProcessTest, ManyCallsOnOneConnectionLeaveItsAuthContextAlone) {
  for (int i = 0; i < 200; ++i) {
    const grpc::Status status = call("/behaviorlib.v1.Coordinator/WriteBelief");
    ASSERT_TRUE(status.ok()) << i << ": " << status.error_message();
  }
  std::lock_guard lock(recorder_.mutex_);
  ASSERT_EQ(recorder_.property_counts.size(), 200u);
  EXPECT_EQ(recorder_.property_counts.front(), recorder_.property_counts.back())
      << "the connection's auth context grew from " << recorder_.property_counts.front() << " to "
      << recorder_.property_counts.back() << " properties";
  EXPECT_EQ(recorder_.callers.front(), "behaviorlib:operator");
  EXPECT_EQ(recorder_.callers.back(), "behaviorlib:operator");
}

// gRPC's auth filter sends a processor's refusal with its code and message
// only; errors::fromGrpc rebuilds the ErrorInfo from the message's stable
// form, so a client sees ROLE_REQUIRED like any other refusal's reason.
TEST_F(AuthorizerInProcessTest, ARefusalGetsItsErrorInfoBackOnTheClient) {
  const grpc::Status refused = call("/behaviorlib.v1.Coordinator/Kill");
  ASSERT_EQ(refused.error_code(), grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(refused.error_message(),
            "/behaviorlib.v1.Coordinator/Kill needs the role safety; 'behaviorlib:operator' has "
            "viewer, operator");
  // If this fails, gRPC now sends the details itself: the rebuilding in
  // fromGrpc and the Python client can go (ROLE_REQUIRED in errors.proto).
  EXPECT_TRUE(refused.error_details().empty());
  const absl::Status status = errors::fromGrpc(refused);
  const auto info = errors::errorInfo(status);
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->reason(), "ROLE_REQUIRED");
  EXPECT_EQ(info->domain(), "behaviorlib.v1");
  EXPECT_EQ(info->metadata().at("role"), "safety");
  EXPECT_EQ(info->metadata().at("identity"), "behaviorlib:operator");
  std::lock_guard lock(recorder_.mutex_);
  EXPECT_TRUE(recorder_.callers.empty()) << "the refused call reached the handler";
}

}  // namespace
}  // namespace behaviorlib::server_kit
