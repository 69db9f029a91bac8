"""The models a gateway serves: their catalog, the pool that keeps at most N of their networks
loaded, and the loader that builds one."""
